"""Errors raised at the data boundary: they name the file and say what was expected."""

from __future__ import annotations

from pathlib import Path

from radar.errors import UserError


class DataError(UserError):
    """A file or payload that is missing, malformed, or not what the reader expected."""

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else Path(path)
        super().__init__(f"{path}: {message}" if path is not None else message)
