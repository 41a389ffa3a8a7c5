"""`magcomp run`: not implemented yet (issue #4)."""

from __future__ import annotations

import argparse

from magcomp.errors import NotImplementedYet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "Not implemented yet: issue #4 fills this in."


def execute(args: argparse.Namespace) -> int:
    raise NotImplementedYet("'run' is not implemented yet (issue #4)")
