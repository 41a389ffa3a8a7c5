"""Per-vehicle summaries from dataset rows (magcomp/fleet/vehicles.py): grouping, flight order, changes,
the mapping file applied afterwards, the ranking."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from magcomp.fleet.discover import VehicleMap
from magcomp.fleet.vehicles import summarise


def _row(
    vehicle: str, n: int, theta: tuple[float, float, float], *, day: int | None, **kw: Any
) -> dict[str, Any]:
    r: dict[str, Any] = {
        "sha256": f"{vehicle}-{n}",
        "path": f"/logs/{vehicle}/f{n:02d}.tlog",
        "file_name": f"f{n:02d}.tlog",
        "vehicle": f"guess:{vehicle}/sys1",
        "vehicle_detected": f"guess:{vehicle}/sys1",
        "status": "ok",
        "compass": 0,
        "applied": True,
        "date_utc": datetime(2026, 3, day, tzinfo=UTC) if day is not None else None,
        "heading_sigma_deg": 1.0,
        "interference_pct": 10.0,
        "warnings": "",
    }
    for axis, v in zip("xyz", theta, strict=True):
        r[f"theta_{axis}_mgauss"] = v
        r[f"theta_sigma_{axis}_mgauss"] = 3.0
    r.update(kw)
    return r


def test_flights_in_date_order_a_change_and_the_ranking() -> None:
    a, b = (-60.0, 20.0, 0.0), (40.0, -20.0, 30.0)
    rows = [_row("v1", i, a if i < 3 else b, day=10 + i) for i in (4, 0, 3, 1, 2, 5)]  # shuffled
    rows += [_row("v2", i, a, day=10 + i) for i in range(5)]
    rows.append(
        {
            "sha256": "v2-bad",
            "path": "/logs/v2/bad.tlog",
            "vehicle": "guess:v2/sys1",
            "status": "failed",
            "error": "no valid MAVLink messages",
            "compass": None,
        }
    )
    vs = summarise(rows)
    assert [v.vehicle for v in vs] == ["guess:v1/sys1", "guess:v2/sys1"]
    v1, v2 = vs
    h = v1.compasses[0]
    assert [f.file_name for f in h.flights] == [f"f{i:02d}.tlog" for i in range(6)]
    assert [(c.index, c.confirmed) for c in h.changes] == [(3, True)]
    assert any("changed" in r and "f03.tlog" in r for r in v1.reasons)
    assert v2.compasses[0].changes == [] and v2.failed == 1 and v2.logs == 6
    assert any("1 of 6 logs failed" in r for r in v2.reasons)


def test_unapplied_flights_are_left_out_of_the_series() -> None:
    rows = [_row("v1", i, (0.0, 0.0, 0.0), day=10 + i) for i in range(4)]
    rows[2].update(applied=False, theta_x_mgauss=500.0)  # no theta learned on that flight
    (v,) = summarise(rows)
    assert len(v.compasses[0].flights) == 3 and v.compasses[0].not_applied == 1
    assert v.compasses[0].changes == []


def test_a_mapping_file_given_later_regroups_the_vehicles() -> None:
    rows = [_row("a", 0, (0.0, 0.0, 0.0), day=1), _row("b", 1, (0.0, 0.0, 0.0), day=2)]
    assert len(summarise([dict(r) for r in rows])) == 2
    vmap = VehicleMap([("lab-quad", ["/logs/*"])])
    (v,) = summarise(rows, vmap)
    assert v.vehicle == "lab-quad" and v.logs == 2 and v.identity_source == "mapping file"


def test_logs_without_a_date_follow_the_dated_ones_by_path() -> None:
    rows = [
        _row("v", 2, (0.0, 0.0, 0.0), day=None),
        _row("v", 1, (0.0, 0.0, 0.0), day=None),
        _row("v", 0, (0.0, 0.0, 0.0), day=5),
    ]
    (v,) = summarise(rows)
    assert [f.file_name for f in v.compasses[0].flights] == ["f00.tlog", "f01.tlog", "f02.tlog"]


def test_flat_rows_have_one_schema_whatever_the_vehicle(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    from magcomp.fleet.store import write_table
    from magcomp.fleet.vehicles import flat_rows

    rows = [{"sha256": "x", "path": "/x.tlog", "vehicle": "failed", "status": "failed", "compass": None}]
    rows += [_row("v1", i, (0.0, 0.0, 0.0), day=1 + i) for i in range(3)]
    vs = summarise(rows)
    flat = flat_rows(vs)
    assert [r["vehicle"] for r in flat] == [v.vehicle for v in vs]
    assert all(set(r) == set(flat[0]) for r in flat)
    write_table(tmp_path / "v.parquet", flat)
    t = pq.read_table(tmp_path / "v.parquet")
    assert t.num_rows == 2 and t.column("flights_applied").to_pylist().count(3) == 1


def _diag(r: dict[str, Any], theta: tuple[float, float, float], hw: float, identifiable: bool = True) -> None:
    r["diagnose_theta_identifiable"] = identifiable
    for axis, v in zip("xyz", theta, strict=True):
        r[f"diagnose_theta_{axis}_mgauss"] = v
        r[f"diagnose_theta_ci95_{axis}_mgauss"] = hw


def test_theta_from_diagnose_follows_its_theta_and_skips_what_it_cannot_identify() -> None:
    """The replay's theta stays flat while diagnose's jumps at flight 3: each source gives its own changes;
    diagnose's half-width becomes a sigma (/1.96) and a flight it calls not identifiable is left out."""
    a, b = (-60.0, 20.0, 0.0), (40.0, -20.0, 30.0)
    rows = [_row("v1", i, a, day=10 + i) for i in range(6)]
    for i, r in enumerate(rows):
        _diag(r, a if i < 3 else b, 5.88, identifiable=i != 1)
    replay = summarise([dict(r) for r in rows])[0].compasses[0]
    diag = summarise([dict(r) for r in rows], theta_from="diagnose")[0].compasses[0]
    assert replay.changes == [] and len(replay.flights) == 6
    assert [f.file_name for f in diag.flights] == ["f00.tlog", "f02.tlog", "f03.tlog", "f04.tlog", "f05.tlog"]
    assert diag.flights[0].sigma == [5.88 / 1.959964] * 3
    assert [(diag.flights[c.index].file_name, c.confirmed) for c in diag.changes] == [("f03.tlog", True)]


def test_history_follows_the_sensor_not_the_slot() -> None:
    """yladzislay's case: an external compass (sensor 466441) in slot 0 and the board's (131594) in slot 1;
    on flights 3 and 4 the external one is unplugged and the board's moves up to slot 0. By slot, slot 0
    would jump between two sensors' thetas (a change that is none); by sensor, neither history changes, and
    the notes say that slot 0 held two sensors. A flight that names no sensor joins its slot's one sensor."""
    ext, board = (-60.0, 20.0, 0.0), (300.0, -150.0, 200.0)
    rows = []
    for i in range(8):
        unplugged = i in (3, 4)
        rows.append(
            _row(
                "v",
                i,
                board if unplugged else ext,
                day=10 + i,
                compass_sensor="131594" if unplugged else "466441",
            )
        )
        if not unplugged:
            rows.append({**_row("v", i, board, day=10 + i, compass_sensor="131594"), "compass": 1})
    assert rows[1]["compass"] == 1
    rows[1]["compass_sensor"] = None  # a log that does not name it: slot 1 holds only 131594, paired with it
    (v,) = summarise(rows)
    by = {h.sensor: h for h in v.compasses}
    assert set(by) == {"466441", "131594"}
    assert len(by["466441"].flights) == 6 and len(by["131594"].flights) == 8
    assert all(h.changes == [] for h in v.compasses), [h.changes for h in v.compasses]
    assert not any("changed" in r for r in v.reasons), v.reasons
    assert any("slot 0 holds different sensors" in n for n in v.notes), v.notes
    assert any("does not name its sensor" in n for n in v.notes), v.notes
    assert by["131594"].compass == 1 and by["131594"].label == "compass 1 (sensor 131594)"
    # without sensors (an older dataset) the history is by slot, as before: slot 0 then "changes"
    for r in rows:
        r.pop("compass_sensor", None)
    (old,) = summarise(rows)
    assert {h.sensor for h in old.compasses} == {None}
    assert any(c.confirmed for h in old.compasses for c in h.changes)


def test_the_vehicle_track_holds_every_vehicle_whose_flights_share_a_bias() -> None:
    """A seeded fleet shaped like benchmarks/fleet_changes.py's finding (docs/fleet.md): 12 vehicles x 17
    flights, theta jumping on every other vehicle, each flight's estimate off by its own noise (the stated
    sigma) plus a bias every flight of the vehicle shares (~4 % of theta, as diagnose's theta has). Each
    flight's own +-2 sigma leaves some vehicle below 90 % of its flights; the vehicle's track (pooled
    between changes, the shared error included) holds the truth on >= 90 % of every vehicle's flights, and
    is narrower than the own interval on the flights that determine theta worst."""
    rng = np.random.default_rng(28)
    gain = np.array([[0.05, 0.03, -0.03], [0.03, -0.02, 0.01], [0.04, 0.0, 0.01]])
    rows, truth = [], {}
    for v in range(12):
        theta0 = rng.uniform(-120, 120, 3)
        theta1 = theta0 + rng.choice([-1, 1], 3) * rng.uniform(60, 120, 3)
        at = int(rng.integers(3, 14)) if v % 2 else 99
        for i in range(17):
            th = theta1 if i >= at else theta0
            sigma = rng.uniform(4.0, 14.0, 3)
            est = th + gain @ th + sigma * rng.standard_normal(3)
            r = _row(f"v{v:02d}", i, tuple(est), day=1 + i)
            for axis, e, s in zip("xyz", est, sigma, strict=True):
                r[f"diagnose_theta_{axis}_mgauss"] = float(e)
                r[f"diagnose_theta_ci95_{axis}_mgauss"] = 1.959964 * float(s)
            r["diagnose_theta_identifiable"] = True
            rows.append(r)
            truth[(f"guess:v{v:02d}/sys1", f"f{i:02d}.tlog")] = th
    own_worst, track_worst, any_outside = 1.0, 1.0, 0
    narrower = []
    for veh in summarise(rows, theta_from="diagnose"):
        h = veh.compasses[0]
        assert h.track is not None and len(h.flights) == 17
        th = np.array([truth[(veh.vehicle, f.file_name)] for f in h.flights])
        x, s = np.array([f.theta for f in h.flights]), np.array([f.sigma for f in h.flights])
        own_worst = min(own_worst, float(np.mean(np.all(np.abs(x - th) <= 2.0 * s, axis=1))))
        inside = np.all((h.track.lower <= th) & (th <= h.track.upper), axis=1)
        track_worst = min(track_worst, float(np.mean(inside)))
        any_outside += int(not np.all(inside))
        wide = s >= np.quantile(s, 0.9, axis=0)
        narrower.append(float(np.median(((h.track.upper - h.track.lower) / (2 * 2.394 * s))[wide])))
    assert own_worst < 0.9  # the flights' own intervals: some vehicle below 90 %
    assert track_worst >= 0.9
    assert any_outside <= 1  # the track holds every flight of a vehicle at 95 %: ~0.6 of 12 expected
    assert float(np.median(narrower)) < 0.95  # on the worst-determined flights: narrower than their own box
