"""Command-line entry point: wiring only. Each subcommand lives in :mod:`magcomp.commands`."""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import sys
from collections.abc import Iterator, Sequence

# Before anything imports numpy. The matrices magcomp solves on its sample path are small (the interim
# calibration fits: ~1000 x 12); OpenBLAS threads them anyway, and on a loaded 2-core machine its
# spinning threads made each fit 30-150 ms instead of ~1 ms (docs/benchmarks.md, replay speed).
# A setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from magcomp import __version__
from magcomp.commands import COMMANDS
from magcomp.errors import MagcompError


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser. ``only``: the command given, whose module alone is imported and whose
    arguments alone are declared (the others are named, without arguments: a command line that names
    ``only`` is parsed the same; ~15 ms of CPU less at each start, the other command modules' imports)."""
    parser = argparse.ArgumentParser(
        prog="magcomp",
        description="Online compensation of throttle-driven magnetometer bias for MAVLink vehicles.",
    )
    parser.add_argument("--version", action="version", version=f"magcomp {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if only is not None and name != only:
            continue
        module = importlib.import_module(f"magcomp.commands.{name}")
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


@contextlib.contextmanager
def interpreter_tuning(command: str) -> Iterator[None]:
    """Process-wide interpreter settings, for the commands that gain from them; set here and nowhere else
    (library code never touches them: issue 13), restored afterwards."""
    if command == "replay":
        # The replay loop allocates many short-lived, acyclic objects (decoded rows, samples, one record
        # per magnetometer sample); reference counting frees them, the cyclic collector finds nothing
        # among them. Measured on this 2-core shared machine, whole `magcomp replay --emit` process, 10 min
        # simulated tlog, CPU time, median of 3-4 interleaved runs with and without: two passes 4.84 vs
        # 5.15 s (6 %), --causal 3.12 vs 3.18 s (2 %); a first series showed no gain (within the noise).
        gc.disable()
        try:
            yield
        finally:
            gc.enable()
    elif command in ("run", "demo"):  # the demo runs the same daemon (a thread) and prints its latency
        # The link's heavy modules (pymavlink and its dialect: thousands of classes) imported now, then
        # moved out of the collector's reach: a full collection over them stalled the sample loop ~40 ms
        # (1 kHz live p99 up to 57 ms; docs/benchmarks.md, live latency). Background threads (refined
        # fits, state writes, housekeeping) hand the interpreter back after 1 ms instead of 5 ms.
        from magcomp.adapters.dialect import ensure_dialect

        ensure_dialect()
        importlib.import_module("pymavlink.mavutil")
        importlib.import_module("magcomp.service.daemon")
        # the in-flight estimator loads scipy's LAPACK at its first solve (core/inflight/base.py: a replay
        # of a log that never learns in flight never needs it); live, that first solve would stall the loop
        from magcomp.core.inflight.base import lapack

        lapack()
        gc.collect()
        gc.freeze()
        old_switch = sys.getswitchinterval()
        sys.setswitchinterval(0.001)
        try:
            yield
        finally:
            sys.setswitchinterval(old_switch)
            gc.unfreeze()
    else:
        yield


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(argv) if argv is not None else sys.argv[1:]
    parser = build_parser(argv[0] if argv and argv[0] in COMMANDS else None)
    args = parser.parse_args(argv)
    if getattr(args, "_module", None) is None:
        parser.print_help()
        return 2
    try:
        with interpreter_tuning(args.command):
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
