"""One module per CLI subcommand: ``add_arguments(parser)`` and ``execute(args) -> int``.

Command modules import heavy dependencies (pymavlink, rerun, scipy) only inside ``execute`` so that
``magcomp --help`` stays fast.
"""

COMMANDS: dict[str, str] = {
    "run": "Attach to a live flight-controller link and publish corrected headings.",
    "replay": "Run the whole pipeline over a tlog or DataFlash log as fast as the machine goes.",
    "simulate": "Generate a synthetic vehicle's MAVLink stream (tlog or live link) with hidden effects.",
    "fit": "Offline least squares of theta on the stationary throttle sweep of a log (Table II).",
    "diagnose": "Compare the model with a measured log, name what it misses, extend it, measure the gain.",
    "fleet": "Every log of every vehicle: one Parquet row per log and compass, theta per vehicle over time.",
    "demo": "Simulator as a fake flight controller + the daemon, no hardware needed.",
    "state": "List the saved states per vehicle and compass; adopt a system id's states for one vehicle.",
    "dialect": "Install the MAGCOMP_HEADING dialect for MAVProxy, mavlogdump.py and pymavlink programs.",
}
