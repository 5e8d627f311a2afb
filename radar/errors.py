"""The project's exception for a user's mistake: a bad argument, file or payload.

Commands report a :class:`UserError` as one line naming what was expected, with exit status 2; any other
exception is a bug and keeps its traceback. It is a ``ValueError``, so code catching bad values still
catches it. :class:`radar.io.errors.DataError` (files and payloads), profile, checkpoint and upload errors
are user errors.
"""

from __future__ import annotations


class UserError(ValueError):
    """A mistake of the user's: the message says what was expected and what was found."""
