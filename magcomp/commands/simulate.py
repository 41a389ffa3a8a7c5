"""`magcomp simulate`: not implemented yet (issue #3)."""

from __future__ import annotations

import argparse

from magcomp.errors import NotImplementedYet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "Not implemented yet: issue #3 fills this in."


def execute(args: argparse.Namespace) -> int:
    raise NotImplementedYet("'simulate' is not implemented yet (issue #3)")
