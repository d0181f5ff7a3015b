"""Errors and exit codes shared by every daemon and command.

The error classes live in ``protocol.errors`` (a client that only decodes needs them
too); this module adds what a process does with them: its exit code.
"""

from __future__ import annotations

import signal
from enum import IntEnum

from protocol.errors import ConfigError, ProtocolError, SumocoError


class ExitCode(IntEnum):
    """Process exit codes of every ``sumoco`` command (README, "Exit codes")."""

    OK = 0
    FAILURE = 1  #: a run failed (a peer went silent, SUMO failed, ...): the message says why
    USAGE = 2  #: bad config, bad scenario, bad arguments or a missing extra: fix and rerun
    PROCESS_FAILED = 3  #: ``sumoco physics --processes N``: a shard process kept failing; the message names it
    INTERRUPTED = 130  #: Ctrl-C / SIGINT


class MissingExtraError(SumocoError):
    """A command needs an optional part that is not installed (``pip install sumoco[x]``)."""

    def __init__(self, command: str, extra: str, module: str) -> None:
        super().__init__(f"`sumoco {command}` needs the {extra!r} extra (module {module!r} is not "
                         f"installed): pip install 'sumoco[{extra}]'")
        self.extra = extra


def exit_code_of(error: BaseException) -> ExitCode:
    """The exit code a command ends with after ``error``."""
    if isinstance(error, (ConfigError, MissingExtraError)):
        return ExitCode.USAGE
    if isinstance(error, KeyboardInterrupt):
        return ExitCode.INTERRUPTED
    return ExitCode.FAILURE


__all__ = ["exit_text", "ConfigError", "ExitCode", "MissingExtraError", "ProtocolError", "SumocoError", "exit_code_of"]


def exit_text(code: int) -> str:
    """How a child process ended, for one-line errors: ``exited with code 1`` / ``was
    killed by SIGKILL`` (a negative code from ``subprocess`` is the signal)."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"
