"""`magcomp state`: the saved calibration and theta per vehicle and compass: list them, or adopt the states of
a system id (written before vehicle identities, or from a log that named none) for one identified vehicle."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "action", choices=("list", "adopt"), help="list the states, or adopt a system id's for one vehicle"
    )
    parser.add_argument("system_id", nargs="?", type=int, help="adopt: the system id whose states to adopt")
    parser.add_argument(
        "uid", nargs="?", help="adopt: the vehicle's unique id (hex, as `state list` or `run` print it)"
    )
    parser.add_argument("--state-dir", metavar="DIR", help="default: $XDG_STATE_HOME/magcomp (as run)")
    parser.add_argument("--force", action="store_true", help="adopt: replace the vehicle's own states")


def execute(args: argparse.Namespace) -> int:
    from magcomp.adapters.state_store import StateStore
    from magcomp.service.console import default_state_dir

    store = StateStore(args.state_dir or default_state_dir())
    if args.action == "list":
        rows = store.list_states()
        if not rows:
            print(f"no saved states in {store.directory}")
        for path, st in rows:
            who = f"vehicle {st.system_id} " + (f"id {st.vehicle_uid}" if st.vehicle_uid else "(no identity)")
            cal = "calibrated" if st.calib_l is not None else "not calibrated"
            theta = ", ".join(f"{v:.1f}" for v in st.theta_mgauss)
            print(f"{who} compass {st.mag_index}: {cal}, theta ({theta}) mgauss  [{path.name}]")
        for w in store.warnings:
            print(f"warning: {w}")
        return 0
    from magcomp.core.identity import normal_uid
    from magcomp.errors import InputError

    if args.system_id is None or args.uid is None:
        raise InputError("adopt needs SYSTEM_ID and UID, e.g. `magcomp state adopt 1 0033002b31395111`")
    uid = normal_uid(args.uid)
    if uid is None:
        raise InputError(f"{args.uid!r} is not a vehicle id (hex, not all zeros)")
    for line in store.adopt(args.system_id, uid, force=args.force):
        print(line)
    return 0
