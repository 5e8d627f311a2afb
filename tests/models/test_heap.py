"""freeze_loaded_heap: the objects alive at start-up leave the cyclic collector's reach; new garbage is still freed."""

from __future__ import annotations

import gc
import weakref

from models.heap import freeze_loaded_heap


class _Node:
    def __init__(self) -> None:
        self.other: _Node | None = None


def test_objects_alive_at_the_call_are_frozen_and_later_cycles_still_collected():
    loaded = [_Node() for _ in range(100)]  # stands for the models loaded at start-up
    try:
        freeze_loaded_heap()
        assert gc.get_freeze_count() >= len(loaded)
        assert not any(gc.is_tracked(node) and node in gc.get_objects() for node in loaded[:3])
        a, b = _Node(), _Node()
        a.other, b.other = b, a  # a reference cycle made after start-up
        gone = weakref.ref(a)
        del a, b
        gc.collect()
        assert gone() is None
    finally:
        gc.unfreeze()
