"""Per-vehicle summaries from dataset rows (magcomp/fleet/vehicles.py): grouping, flight order, changes,
the mapping file applied afterwards, the ranking."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

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
