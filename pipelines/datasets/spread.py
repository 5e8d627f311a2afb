"""Which frames a job scores when it may not score them all: evenly spread over the split."""

from __future__ import annotations

import numpy as np


def spread(n: int, k: int) -> list[int]:
    """``k`` evenly spread indices of ``range(n)``, ascending (all when ``k >= n``; none when ``k <= 0``)."""
    if k <= 0 or n == 0:
        return []
    return sorted({int(i) for i in np.linspace(0, n - 1, min(k, n)).round()})


def subset(n: int, limit: int) -> list[int]:
    """:func:`spread` with ``limit`` 0 meaning every index (the ``--max-frames 0`` convention)."""
    return list(range(n)) if not limit or limit >= n else spread(n, limit)
