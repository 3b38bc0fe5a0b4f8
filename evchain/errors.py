"""One error hierarchy: every message names the culprit, the rule and the fix.

The CLI turns an :class:`EvchainError` into one line on stderr and exit code 2;
anything else is a bug and shows its traceback.
"""

from __future__ import annotations


class EvchainError(Exception):
    """Base of all errors a user can cause and fix."""


class ConfigError(EvchainError):
    """A pipeline file or override is wrong: names file:line:column and the key."""

    def __init__(self, message: str, *, file: str | None = None, line: int | None = None,
                 column: int | None = None, key: str | None = None):
        self.file, self.line, self.column, self.key = file, line, column, key
        where = ""
        if file is not None:
            where = str(file)
            if line is not None:
                where += f":{line}"
                if column is not None:
                    where += f":{column}"
            where += ": "
        if key:
            where += f"{key}: "
        super().__init__(where + message)


class WiringError(ConfigError):
    """Two neighbouring stages of a chain disagree on the packet type."""


class PluginError(EvchainError):
    """A plugin could not be loaded or registers something invalid (names its distribution)."""


class DataError(EvchainError):
    """An input file or packet breaks the format: names the file, offset or record, and what was
    expected."""


class FilterError(EvchainError):
    """A filter failed while running: names the filter, the packet's time slice and the cause.

    ``internal`` is true when the cause is not a user mistake but a bug (an unexpected exception).
    """

    def __init__(self, message: str, *, internal: bool = False):
        super().__init__(message)
        self.internal = internal


class MissingBenchInput(EvchainError):
    """A benchmark row's cached input (rendered events, flow) is not made yet: names the input
    and the ``evchain bench --prepare`` command that makes it."""


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by SIGINT (Ctrl-C) after finishing cleanly: every filter was flushed and
    closed, the outputs are complete for the stream up to ``t_us`` and ``report.json`` says
    ``interrupted``. A :class:`KeyboardInterrupt`, so that callers stop as they would on Ctrl-C
    (a sweep does not go on to its next run); ``result`` is the run's
    :class:`~evchain.core.chain.RunResult`."""

    def __init__(self, message: str, result=None, t_us: int | None = None):
        super().__init__(message)
        self.result, self.t_us = result, t_us
