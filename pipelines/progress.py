"""Progress of long work: a tqdm bar on a terminal, plain lines elsewhere (a log, a pipe, CI).

tqdm redraws its bar with carriage returns, which a log file keeps as one endless line; when stderr is not a
terminal :class:`PlainProgress` writes ``desc: 12/40 frame (30 %), 8.1 s`` as whole lines instead, at most one
every :data:`LINE_EVERY_S` seconds (and the last one), so a long step never looks silent and never floods.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TextIO

from tqdm import tqdm

LINE_EVERY_S = 5.0
_last_line_at = [time.perf_counter()]  # when this process last wrote a progress line (see seconds_since_line)


def note_line() -> None:
    """Record that a line of progress was just written (by a bar, or by a caller's own report)."""
    _last_line_at[0] = time.perf_counter()


def seconds_since_line() -> float:
    """Seconds since the last progress line of this process: a heartbeat speaks only when this grows. A visible
    tqdm bar on a terminal counts as a line written now (it redraws itself)."""
    if any(not getattr(bar, "disable", True) for bar in list(getattr(tqdm, "_instances", ()))):
        note_line()
    return time.perf_counter() - _last_line_at[0]


class PlainProgress:
    """The subset of tqdm's interface the pipelines use (iterate, update, set_postfix, close, context manager)."""

    def __init__(self, iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str = "",
                 unit: str = "it", initial: int = 0, stream: TextIO | None = None,
                 every_s: float = LINE_EVERY_S) -> None:
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.unit, self.n = desc, unit, initial
        self.stream = stream or sys.stderr
        self.every_s = every_s
        self.postfix = ""
        self.started = self.last = time.perf_counter()
        self.closed = False

    def __iter__(self) -> Iterator[Any]:
        assert self.iterable is not None
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_postfix(self, **values: Any) -> None:
        self.postfix = ", ".join(f"{k} {v}" for k, v in values.items())

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if now - self.last >= self.every_s:
            self._line(now)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._line(time.perf_counter())

    def _line(self, now: float) -> None:
        self.last = now
        done = f"{self.n}/{self.total}" if self.total else f"{self.n}"
        share = f" ({100 * self.n / self.total:.0f} %)" if self.total else ""
        extra = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {done} {self.unit}{share}, {now - self.started:.1f} s{extra}", file=self.stream,
              flush=True)
        note_line()


def progress(iterable: Iterable[Any] | None = None, *, disable: bool = False, **kwargs: Any) -> Any:
    """A tqdm bar when stderr is a terminal, else :class:`PlainProgress` lines; nothing shown when ``disable``
    (then tqdm's disabled bar, which only iterates)."""
    if disable or sys.stderr.isatty():
        return tqdm(iterable, disable=disable, **kwargs)
    plain = {k: v for k, v in kwargs.items() if k in ("total", "desc", "unit", "initial")}
    return PlainProgress(iterable, **plain)
