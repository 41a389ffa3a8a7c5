"""`magcomp diagnose`: not implemented yet (issue #6)."""

from __future__ import annotations

import argparse

from magcomp.errors import NotImplementedYet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "Not implemented yet: issue #6 fills this in."


def execute(args: argparse.Namespace) -> int:
    raise NotImplementedYet("'diagnose' is not implemented yet (issue #6)")
