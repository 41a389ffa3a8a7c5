"""`magcomp fleet`: every log of every vehicle -> one Parquet dataset (one row per log and compass), each
vehicle's theta over time, its changes, and the vehicles to inspect first. `magcomp fleet report DIR`:
the same as one static HTML page."""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path
from typing import Any

from magcomp.commands import options

DEFAULT_OUT = "magcomp-fleet"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "paths",
        metavar="PATH",
        nargs="+",
        help="logs (.tlog, .bin, .log, .ulg) or folders searched recursively; `fleet report DIR` writes the "
        "HTML report of a finished DIR instead",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=DEFAULT_OUT,
        help=f"the results folder (default {DEFAULT_OUT}): DIR/logs/ is the Parquet dataset",
    )
    parser.add_argument(
        "--vehicles", metavar="FILE.toml", help='name vehicles: [vehicles] name = ["path or id pattern", ...]'
    )
    options.add_config(parser, help="TOML configuration for the replays")
    parser.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="run on an existing Dask cluster (its workers must see the logs at the same paths)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="local cluster: N worker processes (default: one per core); 0: in this process",
    )
    parser.add_argument(
        "--memory-limit",
        default="auto",
        metavar="SIZE",
        help="per local worker, e.g. 2GiB (default auto: the machine's memory / workers)",
    )
    again = parser.add_mutually_exclusive_group()
    again.add_argument("--rerun-all", action="store_true", help="analyse every log again")
    again.add_argument(
        "--rerun-outdated",
        action="store_true",
        help="analyse again the logs a different magcomp version analysed",
    )
    parser.add_argument(
        "--html", metavar="FILE.html", help="report: where to write it (default DIR/report.html)"
    )
    parser.add_argument(
        "--no-diagnose",
        action="store_true",
        help="the replay's rows only, without `magcomp diagnose`'s findings, theta and parameter files "
        "(40-50 %% less CPU per log, docs/fleet.md)",
    )
    parser.add_argument(
        "--theta-from",
        choices=("auto", "diagnose", "replay"),
        default="auto",
        help="whose theta per flight the vehicles' history and changes follow: diagnose's (its 95 %% "
        "interval) or the replay's correction; auto (default): diagnose's where the rows have it",
    )
    options.add_verbose(parser, help="the replays' log lines")


def execute(args: argparse.Namespace) -> int:
    from magcomp.errors import InputError

    level = logging.INFO if args.verbose else logging.ERROR
    logging.getLogger("magcomp").setLevel(level)
    if args.paths[0] == "report":
        if len(args.paths) != 2:
            raise InputError("usage: magcomp fleet report DIR")
        return _report(Path(args.paths[1]), args)
    if args.html:
        raise InputError("--html goes with `magcomp fleet report DIR`")
    if args.workers is not None and args.workers < 0:
        raise InputError(f"--workers {args.workers}: expected 0 or more")
    if args.memory_limit != "auto":
        from dask.utils import parse_bytes

        try:
            if parse_bytes(args.memory_limit) <= 0:
                raise ValueError
        except (ValueError, TypeError):
            raise InputError(f"--memory-limit {args.memory_limit}: expected a size (2GiB) or auto") from None
    if args.scheduler is not None and args.workers is not None:
        raise InputError("--workers is for the local cluster; an existing cluster (--scheduler) has its own")
    if args.scheduler is not None and not args.scheduler.startswith(
        ("tcp://", "tls://", "ucx://", "inproc://")
    ):
        raise InputError(f"--scheduler {args.scheduler}: expected an address like tcp://HOST:8786")
    return _run(args)


def _run(args: argparse.Namespace) -> int:
    from magcomp.adapters.config import load_config
    from magcomp.errors import InputError
    from magcomp.fleet import engine
    from magcomp.fleet.discover import find_logs, load_vehicle_map

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    vmap = load_vehicle_map(args.vehicles)
    load_config(args.config)  # a bad configuration: one line now, not one failure row per log
    logs = find_logs(args.paths, exclude=out)
    if not logs:
        raise InputError(f"no logs (.tlog, .bin, .log, .ulg) under {' '.join(args.paths)}")
    rerun = "all" if args.rerun_all else "outdated" if args.rerun_outdated else "none"
    plan = engine.plan(logs, out, rerun=rerun, config=args.config, diagnose=not args.no_diagnose)
    where = args.scheduler or ("this process" if args.workers == 0 else "a local Dask cluster")
    skipped = f", {plan.skipped} done before (skipped)" if plan.skipped else ""
    dups = f", {plan.duplicates} duplicate file(s)" if plan.duplicates else ""
    print(f"{plan.found} logs found{skipped}{dups}; analysing {len(plan.tasks)} on {where}", flush=True)
    if plan.outdated_kept:
        print(
            f"note: {plan.outdated_kept} of the skipped logs were analysed by another magcomp version "
            "(--rerun-outdated analyses them again)"
        )
    if plan.tasks:
        st = engine.run(
            plan.tasks,
            out,
            scheduler=args.scheduler,
            workers=args.workers,
            memory_limit=args.memory_limit,
            vmap=vmap,
        )
        rate = 60.0 * st.analysed / st.wall_s if st.wall_s > 0 else 0.0
        print(
            f"analysed {st.analysed} logs ({st.rows} rows): {st.ok} ok, {st.failed} failed, "
            f"in {st.wall_s:.1f} s on {st.workers} worker(s): {rate:.1f} logs/min, "
            f"{st.cpu_s / max(st.analysed, 1):.2f} s CPU per log"
        )
    vehicles = _vehicles(out, vmap, args.theta_from)
    print(f"results: {out / 'logs'} (Parquet, per log), {out / 'vehicles.parquet'}, {out / 'vehicles.json'}")
    n_params = sum(1 for v in vehicles if v.params)
    if n_params:
        print(f"compensation parameters for {n_params} vehicle(s): {out / 'params'}")
    _print_inspect(vehicles)
    return 0


def _vehicles(out: Path, vmap: Any, theta_from: str = "auto") -> list[Any]:
    from magcomp.fleet import store
    from magcomp.fleet.vehicles import flat_rows, summarise

    rows = store.read_rows(out).to_pylist()
    if theta_from == "auto":  # diagnose's interval covers the truth at its level, the replay's less (docs)
        theta_from = "diagnose" if any(r.get("diagnose_status") == "ok" for r in rows) else "replay"
    vehicles = summarise(rows, vmap, theta_from=theta_from)
    _write_params(out, vehicles)
    doc = {"theta_from": theta_from, "vehicles": [v.to_json() for v in vehicles]}
    tmp = out / ".vehicles.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, out / "vehicles.json")
    store.write_table(out / "vehicles.parquet", flat_rows(vehicles))
    return vehicles


def _write_params(out: Path, vehicles: list[Any]) -> None:
    """Per vehicle with compensation parameters, the files ``magcomp diagnose --params-out`` writes:
    OUT/params/VEHICLE.params (QGroundControl) for PX4 and ArduPilot, and VEHICLE.param (Mission Planner)
    for ArduPilot; the folder holds only the current ones."""
    import re

    from magcomp.adapters.param_files import write_param_file

    folder = out / "params"
    for old in folder.glob("*.param*") if folder.is_dir() else []:
        old.unlink()
    for v in vehicles:
        if not v.params:
            continue
        folder.mkdir(parents=True, exist_ok=True)
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", v.vehicle).strip("_") or "vehicle"
        px4 = v.params["autopilot"] == "PX4"
        files = [folder / f"{stem}.params"] + ([] if px4 else [folder / f"{stem}.param"])
        for f in files:
            write_param_file(f, v.params["values"], stack="PX4 Pro" if px4 else "ArduPilot")
        v.params["files"] = [str(f) for f in files]


def _print_inspect(vehicles: list[Any], limit: int = 10) -> None:
    from magcomp.fleet.vehicles import track_text

    if not vehicles:
        return
    print(f"vehicles, most worth inspecting first ({len(vehicles)}):")
    for v in vehicles[:limit]:
        thetas = "; ".join(
            f"{h.label} theta now {track_text(h)} mgauss"
            for h in v.compasses
            if h.level is not None
        )
        print(f"  {v.vehicle}: {v.logs} logs, score {v.score:.0f}" + (f"; {thetas}" if thetas else ""))
        for r in v.reasons:
            print(f"    - {r}")
    if len(vehicles) > limit:
        print(f"  ... {len(vehicles) - limit} more in vehicles.json")


def _report(out: Path, args: argparse.Namespace) -> int:
    from magcomp.errors import InputError
    from magcomp.fleet import store
    from magcomp.fleet.discover import load_vehicle_map

    if not store.logs_dir(out).is_dir():
        raise InputError(f"{out}: no fleet results here (run `magcomp fleet PATH... --out {out}` first)")
    from magcomp.fleet.report import write_report

    vmap = load_vehicle_map(args.vehicles)
    vehicles = _vehicles(out, vmap, args.theta_from)
    rows = store.read_rows(out).to_pylist()
    html = Path(args.html) if args.html else out / "report.html"
    write_report(html, vehicles, rows)
    print(f"wrote {html} ({len(vehicles)} vehicles, {len({r['sha256'] for r in rows})} logs)")
    return 0
