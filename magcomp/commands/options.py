"""The options several commands share, added with each command's own help text."""

from __future__ import annotations

import argparse

#: ``--config``'s help where nothing more is to be said
CONFIG_HELP = "TOML configuration (default: built-in defaults)"


def add_config(parser: argparse.ArgumentParser, help: str = CONFIG_HELP) -> None:
    parser.add_argument("--config", metavar="FILE", help=help)


def add_state_dir(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("--state-dir", metavar="DIR", help=help)


def add_json(parser: argparse.ArgumentParser, help: str, metavar: str = "SUMMARY.json") -> None:
    parser.add_argument("--json", metavar=metavar, help=help)


def add_verbose(parser: argparse.ArgumentParser, help: str = "debug log lines") -> None:
    parser.add_argument("-v", "--verbose", action="store_true", help=help)
