"""Exceptions that the CLI turns into one-line messages and exit codes (the library never exits)."""


class MagcompError(Exception):
    """A user-facing failure with a one-line message. ``exit_code`` is what the CLI returns."""

    exit_code: int = 1

    def __init__(self, message: str, exit_code: int | None = None) -> None:
        super().__init__(message)
        if exit_code is not None:
            self.exit_code = exit_code


class InputError(MagcompError):
    """Unreadable, empty or malformed input (files, links, configuration)."""


class NotImplementedYet(MagcompError):
    """A subcommand that a later issue fills in."""

    exit_code = 2
