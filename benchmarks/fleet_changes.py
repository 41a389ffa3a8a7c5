"""Change detection on a simulated fleet: V vehicles x F flights, each vehicle its own theta (and seed per
flight), and on every other vehicle one hidden change (theta jumps at a known flight). Runs `magcomp
fleet` (its engine, in this process or on a local cluster) and scores: changes found at the right flight,
changes flagged on vehicles without one, and how often each flight's printed theta interval covers the
truth at its stated level: the replay's theta sigma (+-1 sigma: 68.3 % per axis; +-2 sigma: 95.4 % per axis,
86.8 % on all three axes at once if the axes were independent) and `diagnose`'s 95 % half-width per axis;
and how often each vehicle's theta track (fleet.vehicles.theta_track: pooled between changes, 95 % over the
whole track) holds the truth, per vehicle, with its widths against diagnose's box (``--ablate``: without
each of its parts). ``--seed`` changes the thetas, the changes and every flight's simulation (seed 0: the
flights of before); ``--jitter`` varies the true theta from flight to flight; ``--save DIR`` keeps the rows
and the truth, ``--rescore DIR`` scores them again without simulating (docs/fleet.md).

    .venv/bin/python benchmarks/fleet_changes.py [--vehicles 10] [--flights 6] [--duration 60] [--workers 0]
        [--seed 0] [--jitter 0] [--save DIR] [--rescore DIR] [--ablate]
"""

from __future__ import annotations

import os

# as magcomp's CLI does, before numpy loads: OpenBLAS threads on small solves only spin on a busy machine
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--flights", type=int, default=6)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=0, help="0: in this process (default)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", help="TOML configuration for the replays (e.g. [output] self_check = false)")
    ap.add_argument(
        "--jitter",
        type=float,
        default=0.0,
        help="flight-to-flight variation of the true theta, mgauss (standard deviation per axis; default 0)",
    )
    ap.add_argument(
        "--save", help="also write the rows (rows.parquet) and the truth (truth.json) to this folder"
    )
    ap.add_argument(
        "--rescore",
        metavar="DIR",
        help="score the rows and truth a --save run wrote (no simulation, no analysis)",
    )
    ap.add_argument(
        "--ablate", action="store_true", help="also score the vehicle track without its parts (docs/fleet.md)"
    )
    args = ap.parse_args()
    if args.rescore:
        return rescore(Path(args.rescore), args.ablate)

    from magcomp.cli import main as cli
    from magcomp.fleet import engine, store
    from magcomp.fleet.discover import VehicleMap, find_logs
    from magcomp.fleet.vehicles import summarise

    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="magcomp-fleet-changes-") as tmp:
        root = Path(tmp)
        truth: dict[str, dict[str, object]] = {}
        t0 = time.perf_counter()
        for v in range(args.vehicles):
            name = f"veh{v:02d}"
            (root / name).mkdir()
            theta0 = rng.uniform(-120, 120, 3)
            change_at = int(rng.integers(2, args.flights - 1)) if v % 2 == 1 else None
            theta1 = theta0 + rng.choice([-1, 1], 3) * rng.uniform(60, 120, 3)
            thetas = []
            logged: list[list[float]] = []  # the same in the frame of the logged field (truth_theta)
            for f in range(args.flights):
                th = theta1 if change_at is not None and f >= change_at else theta0
                if args.jitter > 0:
                    th = th + rng.normal(0.0, args.jitter, 3)
                thetas.append(th.tolist())
                year = 2026.0 + 0.05 * (f + 1)
                rc = cli(
                    [
                        "simulate",
                        "--scenario",
                        "ordinary",
                        "--duration",
                        str(args.duration),
                        "--compasses",
                        "1",
                        "--seed",
                        str(100_000 * args.seed + 1000 * v + f),  # seed 0: the flights of before
                        "--year",
                        f"{year:.3f}",
                        "--set",
                        "theta_mgauss=" + ",".join(f"{x:.1f}" for x in th),
                        "--out",
                        str(root / name / f"flight{f:02d}.tlog"),
                    ]
                )
                assert rc == 0
                sim = json.loads((root / name / f"flight{f:02d}.truth.json").read_text())
                logged.append(sim["compasses"][0]["logged_frame"]["theta_logged_mgauss"])
            truth[name] = {"change_at": change_at, "thetas": thetas, "thetas_logged": logged}
        print(f"simulated {args.vehicles} x {args.flights} flights in {time.perf_counter() - t0:.0f} s")
        out = root / "out"
        logs = find_logs([str(root)], exclude=out)
        p = engine.plan(logs, out, config=args.config)
        vmap = VehicleMap([(n, [f"*/{n}/*"]) for n in truth])
        st = engine.run(p.tasks, out, workers=args.workers, vmap=vmap, progress=False)
        print(
            f"analysed {st.analysed} logs in {st.wall_s:.0f} s ({st.failed} failed), "
            f"{st.cpu_s / max(st.analysed, 1):.2f} s CPU per log"
        )
        table = store.read_rows(out)
        rows = table.to_pylist()
        if args.save:
            import pyarrow.parquet as pq

            save = Path(args.save)
            save.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, save / "rows.parquet")
            (save / "truth.json").write_text(json.dumps(truth, indent=1))
        vehicles = {v.vehicle: v for v in summarise(rows)}
        hits = misses = wrong_flight = false_flags = 0
        covered = total = applied = 0
        pairs: list[tuple[dict[str, object], np.ndarray]] = []
        for name, t in truth.items():
            veh = vehicles[name]
            h = veh.compasses[0] if veh.compasses else None
            found = [c for c in (h.changes if h else []) if c.confirmed]
            idx = [h.flights[c.index].file_name for c in found] if h else []
            want = t["change_at"]
            if want is None:
                false_flags += len(found)
            else:
                target = f"flight{want:02d}.tlog"
                if target in idx:
                    hits += 1
                    false_flags += len(found) - 1
                elif found:
                    wrong_flight += 1
                    false_flags += len(found) - 1
                else:
                    misses += 1
            mine = sorted(
                (r for r in rows if r["vehicle"] == name and r["status"] == "ok"), key=lambda r: r["path"]
            )
            for r in mine:
                f = int(r["file_name"][6:8])
                th = truth_theta(t, f)
                pairs.append((r, th))
                total += 1
                if not r["applied"] or r["theta_sigma_x_mgauss"] is None:
                    continue
                applied += 1
                est = np.array([r["theta_x_mgauss"], r["theta_y_mgauss"], r["theta_z_mgauss"]])
                sig = np.array(
                    [r["theta_sigma_x_mgauss"], r["theta_sigma_y_mgauss"], r["theta_sigma_z_mgauss"]]
                )
                covered += bool(np.all(np.abs(est - th) <= 2 * sig))
            print(
                f"{name}: change {want}, flagged at {idx}, "
                f"{json.dumps([len(h.flights) if h else 0])} flights applied"
            )
        n_changed = sum(1 for t in truth.values() if t["change_at"] is not None)
        print(
            f"changes found at the right flight: {hits}/{n_changed}; at another flight: {wrong_flight}; "
            f"missed: {misses}; flagged on vehicles without one (or extra): {false_flags}"
        )
        print(
            f"theta applied on {applied}/{total} flights; +-2 sigma (all three axes) covers the truth on "
            f"{covered}/{applied} = {100 * covered / max(applied, 1):.0f} %"
        )
        print("with diagnose's theta per flight (fleet.vehicles.summarise theta_from='diagnose'): "
              + change_score(rows, truth, "diagnose"))  # fmt: skip
        applied_pairs = [(r, th) for r, th in pairs if r["applied"]]
        for line in coverage_lines(
            applied_pairs, "theta", "theta_sigma", "replay sigma", [(1.0, 68.3), (2.0, 95.4)]
        ):
            print(line)
        for line in coverage_lines(
            pairs, "diagnose_theta", "diagnose_theta_ci95", "diagnose ci95", [(1.0, 95.0)]
        ):
            print(line)
        # the joint box: its "all three axes" share is the one stated at 95 %
        for line in coverage_lines(
            pairs, "diagnose_theta", "diagnose_theta_ci95_joint", "diagnose joint ci95", [(1.0, 95.0)]
        ):
            print(line)
        for line in track_lines(rows, truth):
            print(line)
        if args.ablate:
            for line in ablation_lines(rows, truth):
                print(line)
    return 0


def truth_theta(t: Any, flight: int) -> np.ndarray:
    """The true theta of a flight in the frame diagnose reports it in and the autopilot takes it in: the
    frame of the logged (autopilot-calibrated) field, ``L^-1 theta`` of the simulator's truth (ArduPilot
    adds COMPASS_MOT x throttle after its offsets and DIA/ODI matrix). A --save folder written before this
    frame was recorded has the body-frame theta only (the simulator's ``theta_mgauss``), used then."""
    key = "thetas_logged" if "thetas_logged" in t else "thetas"
    return np.array(t[key][flight], dtype=float)


def rescore(saved: Path, ablate: bool) -> int:
    """Print the scores of the rows and truth a ``--save`` run wrote."""
    import pyarrow.parquet as pq

    if not (saved / "rows.parquet").is_file() or not (saved / "truth.json").is_file():
        print(f"{saved}: no rows.parquet and truth.json here (write them with --save)", file=sys.stderr)
        return 2
    rows = pq.read_table(saved / "rows.parquet").to_pylist()
    truth = json.loads((saved / "truth.json").read_text())
    print(f"{saved}: {len(rows)} rows, {len(truth)} vehicles")
    for line in score_lines(rows, truth, ablate):
        print(line)
    return 0


def score_lines(rows: list[dict[str, Any]], truth: dict[str, Any], ablate: bool) -> list[str]:
    """The scores of saved rows: changes, diagnose's joint box, the vehicle track (and its ablations)."""
    pairs = []
    for r in rows:
        if r["status"] == "ok" and r["vehicle"] in truth:
            pairs.append((r, truth_theta(truth[r["vehicle"]], int(r["file_name"][6:8]))))
    out = ["with diagnose's theta per flight: " + change_score(rows, truth, "diagnose")]
    out += coverage_lines(
        pairs, "diagnose_theta", "diagnose_theta_ci95_joint", "diagnose joint ci95", [(1.0, 95.0)]
    )
    out += track_lines(rows, truth)
    if ablate:
        out += ablation_lines(rows, truth)
    return out


def _track_coverage(
    rows: list[dict[str, Any]], truth: dict[str, Any], track: Callable[..., Any] | None = None
) -> tuple[dict[str, list[bool]], list[np.ndarray], list[np.ndarray]]:
    """Per vehicle, per flight of its track: whether the track's box holds the truth on all three axes; the
    track's half-widths and diagnose's joint half-widths of the same flights. ``track(x, s, changes)``:
    another track than the shipped one (fleet.vehicles.theta_track)."""
    from magcomp.fleet.vehicles import summarise

    by_file = {(str(r["vehicle"]), str(r["file_name"])): r for r in rows if r["status"] == "ok"}
    inside: dict[str, list[bool]] = {}
    widths: list[np.ndarray] = []
    diag: list[np.ndarray] = []
    for v in summarise([dict(r) for r in rows], theta_from="diagnose"):
        if v.vehicle not in truth or not v.compasses:
            continue
        h = v.compasses[0]
        t = h.track
        if track is not None and h.flights:
            x = np.array([f.theta for f in h.flights])
            sd = np.array([f.sigma for f in h.flights])
            t = track(x, sd, h.changes)
        if t is None:
            continue
        for i, f in enumerate(h.flights):
            th = truth_theta(truth[v.vehicle], int(f.file_name[6:8]))
            inside.setdefault(v.vehicle, []).append(bool(np.all((t.lower[i] <= th) & (th <= t.upper[i]))))
            widths.append((t.upper[i] - t.lower[i]) / 2.0)
            r = by_file[(v.vehicle, f.file_name)]
            diag.append(np.array([r[f"diagnose_theta_ci95_joint_{a}_mgauss"] for a in "xyz"], dtype=float))
    return inside, widths, diag


def track_lines(
    rows: list[dict[str, Any]],
    truth: dict[str, Any],
    label: str = "vehicle track",
    track: Callable[..., Any] | None = None,
) -> list[str]:
    """How often the vehicle track (fleet.vehicles.theta_track) holds the truth: overall, per vehicle, the
    vehicles where it misses any flight (stated: at most 5 %), and its widths against diagnose's box."""
    inside, widths, diag = _track_coverage(rows, truth, track)
    if not inside:
        return [f"{label}: no vehicle with a track"]
    per = {v: float(np.mean(x)) for v, x in inside.items()}
    worst = min(per, key=lambda v: per[v])
    n = sum(len(x) for x in inside.values())
    ratio = np.median(np.array(widths) / np.array(diag), axis=0)
    return [
        f"{label}: holds the truth on all three axes on {sum(sum(x) for x in inside.values())}/{n} flights "
        f"({100 * sum(sum(x) for x in inside.values()) / n:.1f} %); per vehicle lowest "
        f"{100 * per[worst]:.0f} % ({worst}), at >= 90 %: {sum(x >= 0.9 for x in per.values())}/{len(per)}; "
        f"vehicles with any flight outside: {sum(not all(x) for x in inside.values())}/{len(per)}",
        "  half-width / diagnose's joint half-width, median per axis x/y/z "
        + "/".join(f"{v:.2f}" for v in ratio)
        + "; median half-width mgauss x/y/z "
        + "/".join(f"{v:.1f}" for v in np.median(np.array(widths), axis=0)),
        "  on the flights whose own box is among the widest 10 % (per axis): half-width / diagnose's, median "
        "x/y/z " + "/".join(f"{v:.2f}" for v in _wide_ratio(np.array(widths), np.array(diag))),
    ]


def _wide_ratio(widths: np.ndarray, diag: np.ndarray) -> list[float]:
    """Per axis: the median track / diagnose half-width over the flights in diagnose's widest 10 %."""
    out = []
    for j in range(3):
        wide = diag[:, j] >= np.quantile(diag[:, j], 0.9)
        out.append(float(np.median(widths[wide, j] / diag[wide, j])))
    return out


def ablation_lines(rows: list[dict[str, Any]], truth: dict[str, Any]) -> list[str]:
    """The track without each of its parts: no systematic term; 95 % per flight (box over the three axes)
    instead of the whole track at 95 %."""
    from magcomp.core.pooling import family_level, pooled_track
    from magcomp.fleet import vehicles as fv

    def make(kind: str, systematic: bool) -> Callable[..., Any]:
        rel, ab = (fv.TRACK_SYSTEMATIC_REL, fv.TRACK_SYSTEMATIC_ABS_MGAUSS) if systematic else (0.0, 0.0)

        def track(x: np.ndarray, s: np.ndarray, changes: list[Any]) -> Any:
            level = family_level(0.95, x.shape[0] if kind == "track" else 1, 3)
            return pooled_track(x, s, [c.index for c in changes], level, rel, ab)

        return track

    out: list[str] = []
    for label, kind, systematic in (
        ("ablation: no systematic term", "track", False),
        ("ablation: 95 % per flight (box over the axes), systematic term kept", "flight", True),
        ("ablation: 95 % per flight (box over the axes), no systematic term", "flight", False),
    ):
        out += track_lines(rows, truth, label, make(kind, systematic))
    return out


def change_score(rows: list[dict[str, object]], truth: dict[str, dict[str, object]], theta_from: str) -> str:
    """Changes found at the right flight / elsewhere / missed / flagged without one, with ``theta_from``."""
    from magcomp.fleet.vehicles import summarise

    vehicles = {v.vehicle: v for v in summarise([dict(r) for r in rows], theta_from=theta_from)}
    hits = wrong = missed = false = used = 0
    for name, t in truth.items():
        h = vehicles[name].compasses[0] if vehicles[name].compasses else None
        used += len(h.flights) if h else 0
        found = [h.flights[c.index].file_name for c in h.changes if c.confirmed] if h else []
        want = t["change_at"]
        if want is None:
            false += len(found)
        elif f"flight{want:02d}.tlog" in found:
            hits, false = hits + 1, false + len(found) - 1
        elif found:
            wrong, false = wrong + 1, false + len(found) - 1
        else:
            missed += 1
    n_changed = sum(1 for t in truth.values() if t["change_at"] is not None)
    return (
        f"{used} flights used; changes at the right flight {hits}/{n_changed}, at another {wrong}, missed "
        f"{missed}; flagged without one (or extra) {false}"
    )


def coverage_lines(
    pairs: list[tuple[dict[str, object], np.ndarray]],
    theta: str,
    width: str,
    label: str,
    levels: list[tuple[float, float]],
) -> list[str]:
    """Per stated level: the share of (flight, axis) whose interval (k x the printed width) covers the
    truth, and of flights covered on all three axes; the median |error| / width per axis."""
    est, hw, veh = [], [], []
    for r, th in pairs:
        e = [r.get(f"{theta}_{a}_mgauss") for a in "xyz"]
        w = [r.get(f"{width}_{a}_mgauss") for a in "xyz"]
        if all(isinstance(v, float) for v in e + w):
            est.append(np.array(e, dtype=float) - th)
            hw.append(np.array(w, dtype=float))
            veh.append(str(r.get("vehicle")))
    if not est:
        return [f"{label}: no flight with an interval"]
    err, wid = np.abs(np.array(est)), np.array(hw)
    ratio = np.median(err / np.maximum(wid, 1e-9), axis=0)
    out = [f"{label}: {len(est)} flights with an interval; median |error| / width per axis x/y/z "
           + "/".join(f"{v:.2f}" for v in ratio)]  # fmt: skip
    for k, stated in levels:
        inside = err <= k * wid
        out.append(
            f"  +-{k:g} x {label}: per axis {100 * inside.mean():.0f} % (stated {stated:g} %; x/y/z "
            + "/".join(f"{100 * v:.0f}" for v in inside.mean(axis=0))
            + f"), all three axes {100 * inside.all(axis=1).mean():.0f} %"
        )
        names = np.array(veh)
        per_vehicle = {v: float(inside.all(axis=1)[names == v].mean()) for v in sorted(set(veh))}
        worst = min(per_vehicle, key=lambda v: per_vehicle[v])
        out.append(
            f"    per vehicle, all three axes: lowest {100 * per_vehicle[worst]:.0f} % ({worst}); at "
            f">= 90 %: {sum(x >= 0.9 for x in per_vehicle.values())}/{len(per_vehicle)}"
        )
    return out


if __name__ == "__main__":
    raise SystemExit(main())
