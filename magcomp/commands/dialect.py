"""`magcomp dialect`: make MAVProxy, mavlogdump.py and any pymavlink program decode MAGCOMP_HEADING.

``install`` writes the generated ``magcomp`` dialect (which includes ardupilotmega) into pymavlink's dialects
folder; afterwards ``--dialect magcomp`` or ``MAVLINK_DIALECT=magcomp`` selects it. ``show`` prints where it
is and how to use it; ``uninstall`` removes it.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("install", "show", "uninstall"), help="what to do")
    parser.add_argument(
        "--dest",
        metavar="DIR",
        help="a pymavlink 'dialects' folder (holding v10/ and v20/); default: the installed pymavlink's",
    )


def usage_lines() -> list[str]:
    from magcomp.adapters.dialect import DIALECT_ENV

    env = " ".join(f"{k}={v}" for k, v in DIALECT_ENV.items())
    return [
        "decode MAGCOMP_HEADING with:",
        "  mavlogdump.py --dialect magcomp --types MAGCOMP_HEADING FILE.tlog",
        "  mavproxy.py --master ... --dialect magcomp",
        f"  or, for any pymavlink program: export {env}",
    ]


def execute(args: argparse.Namespace) -> int:
    from magcomp.adapters import dialect

    dest = Path(args.dest) if args.dest else None
    if args.action == "install":
        written = dialect.install_dialect(dest)
        print(f"installed the magcomp MAVLink dialect into {written[0].parent.parent}")
        for line in usage_lines():
            print(line)
    elif args.action == "uninstall":
        removed = dialect.uninstall_dialect(dest)
        where = dest or dialect.default_install_dir()
        print(f"removed {len(removed)} file(s) from {where}" if removed else f"not installed in {where}")
    else:
        found = dialect.installed_files(dest)
        where = dest or dialect.default_install_dir()
        if not found:
            print(f"the magcomp dialect is not installed in {where}: run `magcomp dialect install`")
            return 1
        print(f"the magcomp dialect is installed in {where}")
        for line in usage_lines():
            print(line)
    return 0
