"""What the service says to clients and writes to its log about names and paths it did not choose: checkpoint paths
without the server's directories (a tenant learns the file, not the layout of the host), and names from radars,
checkpoints or requests with their control characters escaped (a CRLF in a radar's name cannot forge a log line or
a header)."""

from __future__ import annotations

import logging
import re

ABSOLUTE_PATH = re.compile(r"(?<![\w.~-])/(?:[^\s'\"/:,;()\[\]]+/)+(?=[^\s'\"/:,;()\[\]]+)")
CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def without_directories(text: str) -> str:
    """``text`` with every absolute path shortened to its file name (``/srv/models/detector.pt`` -> ``detector.pt``)."""
    return ABSOLUTE_PATH.sub("", text)


def printable(text: str) -> str:
    """``text`` with control characters (CR, LF, ESC, ...) escaped as ``\\xNN`` / ``\\uNNNN``: safe in one log line."""
    return CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


class EscapeControlCharacters(logging.Filter):
    """A log handler's filter: each record's message with its control characters escaped (:func:`printable`), so a
    CR/LF in a name it quotes stays inside its line."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if CONTROL.search(message):
            record.msg, record.args = printable(message), None
        return True
