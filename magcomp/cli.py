"""Command-line entry point: wiring only. Each subcommand lives in :mod:`magcomp.commands`."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

# Before anything imports numpy. The matrices magcomp solves on its sample path are small (the interim
# calibration fits: ~1000 x 12); OpenBLAS threads them anyway, and on a loaded 2-core machine its
# spinning threads made each fit 30-150 ms instead of ~1 ms (docs/benchmarks.md, replay speed).
# A setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from magcomp import __version__
from magcomp.commands import COMMANDS
from magcomp.errors import MagcompError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magcomp",
        description="Online compensation of throttle-driven magnetometer bias for MAVLink vehicles.",
    )
    parser.add_argument("--version", action="version", version=f"magcomp {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        module = importlib.import_module(f"magcomp.commands.{name}")
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(list(argv) if argv is not None else None)
    if getattr(args, "_module", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args._module.execute(args))
    except MagcompError as exc:
        print(f"magcomp {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"magcomp {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
