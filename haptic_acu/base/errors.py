"""Errors meant for the person at the terminal.

A :class:`UserError` is bad input (a malformed file, a bad key, a missing device library): the CLI
prints its message as one line on stderr, with no traceback, and exits with ``exit_status`` (2).
"""


class UserError(Exception):
    """Bad input. ``str(err)`` is the whole one-line message (it names the file, line or key)."""

    exit_status = 2

    def __init__(self, message: str, exit_status: int = 2):
        super().__init__(message.replace("\n", " "))
        self.exit_status = exit_status


class DeviceFault(Exception):
    """A device stopped answering, reported an error or returned non-finite data mid-session."""
