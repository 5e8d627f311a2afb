"""The project's exception for a user's mistake: a bad argument, file or payload.

Commands report a :class:`UserError` as one line naming what was expected, with exit status 2; any other
exception is a bug and keeps its traceback. It is a ``ValueError``, so code catching bad values still
catches it. :class:`DataError` (files and payloads), profile, checkpoint and upload errors
are user errors.
"""

from __future__ import annotations

from pathlib import Path


class UserError(ValueError):
    """A mistake of the user's: the message says what was expected and what was found."""


class DataError(UserError):
    """A file or payload that is missing, malformed, or not what the reader expected: the message names the file."""

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)
