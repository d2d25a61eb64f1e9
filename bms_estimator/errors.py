"""The project's exceptions, and the command line's exit codes.

Every error a user can cause derives from :class:`BmsEstimatorError`; its message is meant
for the user (one line, or a header and one line per problem) and never needs a traceback.
"""

from __future__ import annotations

__all__ = [
    "EXIT_DATA",
    "EXIT_RUNTIME",
    "EXIT_USAGE",
    "BmsEstimatorError",
    "CanBusError",
    "ConfigError",
    "DataError",
    "MappingError",
    "UsageError",
    "one_line_error",
]

#: exit codes of ``bms-estimator``: 0 = done
EXIT_RUNTIME = 1  # something failed while running (CAN bus, broker, the service itself)
EXIT_USAGE = 2  # the command line or the configuration asks for something invalid
EXIT_DATA = 3  # an input file (recording, log, OCV table) is unreadable or malformed


class BmsEstimatorError(Exception):
    """Base of the project's errors. ``problems`` holds one line per problem (may be empty)."""

    exit_code = EXIT_RUNTIME

    def __init__(self, header: str, problems: list[str] | None = None) -> None:
        self.header = header
        self.problems = list(problems or [])
        super().__init__("\n".join([header, *("  " + p for p in self.problems)]))


class ConfigError(BmsEstimatorError, ValueError):
    """Invalid or unreadable configuration: ``problems`` has one ``section.key: message`` line each."""

    exit_code = EXIT_USAGE


class MappingError(ConfigError):
    """A CAN input mapping that cannot be loaded or does not fit the DBC; one problem per line."""


class DataError(BmsEstimatorError, ValueError):
    """An input file is malformed; the message names the file and the problem."""

    exit_code = EXIT_DATA


class UsageError(BmsEstimatorError, ValueError):
    """The command line asks for something that cannot be done (a bad option value)."""

    exit_code = EXIT_USAGE


class CanBusError(BmsEstimatorError):
    """A CAN bus could not be opened or used (the message is one line)."""


def one_line_error(exc: BaseException) -> str:
    """``Type: first line of the message`` - what a status line or a log field shows."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
