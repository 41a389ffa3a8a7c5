"""`magcomp fit`: not implemented yet (issue #2)."""

from __future__ import annotations

import argparse

from magcomp.errors import NotImplementedYet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "Not implemented yet: issue #2 fills this in."


def execute(args: argparse.Namespace) -> int:
    raise NotImplementedYet("'fit' is not implemented yet (issue #2)")
