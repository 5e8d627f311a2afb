"""Wall-clock timing of one call, repeated: what every latency benchmark reports (never asserted)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def time_call(call: Callable[[], object], repeats: int, *, warmup: int = 1) -> dict[str, float | int]:
    """``call()`` ``warmup`` times untimed, then ``repeats`` times: median and minimum seconds."""
    for _ in range(warmup):
        call()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats}
