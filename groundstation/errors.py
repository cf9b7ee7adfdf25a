"""How ``pmon gcs`` fails: the process exit codes, ``GcsError`` (a command refused or failed, or
nothing heard) and ``UsageError`` (a bad argument or value), each carrying the one line that says
why (docs/OPERATING.md)."""
from __future__ import annotations

OK, FAILED, USAGE, TIMEOUT, INTERRUPTED = 0, 1, 2, 3, 130  # exit codes


class GcsError(Exception):
    """A command failed; ``code`` is the process exit code (FAILED: refused/failed, TIMEOUT)."""

    def __init__(self, message: str, code: int = FAILED):
        super().__init__(message)
        self.code = code


class UsageError(Exception):
    """A bad argument or value (exit code USAGE)."""
