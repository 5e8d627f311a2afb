"""The example sequences of ``GET /v1/examples``: each simulated once per radar and example, whatever the number of
requests asking for it at once, and kept within a byte budget.

A sequence (every frame's ``.npy`` bytes and its first frame's objects) is made by the first request that needs it;
concurrent requests for the same one wait for that simulation instead of running their own (single flight), and
simulations run one at a time service-wide, so examples never take more than one core whatever the load. Sequences
are kept, least recently used first out, within ``max_bytes`` (the last one made is always kept). Examples are
not billed: their cost is bounded by the number of radars served times the number of examples.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from radar.profiles import RadarProfile
from radar.simulate import simulate_sequence
from radar.simulate.targets import CLASS_MODELS


class NoExamples(Exception):
    """The radar has classes the simulator cannot place (its message names them)."""


@dataclass(frozen=True)
class ExampleSequence:
    """One example: every frame as ``.npy`` bytes, and the first frame's cube shape, dtype and objects."""

    frames: tuple[bytes, ...]
    shape: tuple[int, ...]
    dtype: str
    objects: tuple  # radar.frame objects of frame 0

    @property
    def nbytes(self) -> int:
        return sum(len(frame) for frame in self.frames)


def unknown_classes(profile: RadarProfile) -> list[str]:
    """The radar's classes the simulator has no scatterer model for."""
    return [name for name in profile.class_names if name not in CLASS_MODELS]


class ExampleCache:
    """Example sequences by (radar fingerprint and name, seed); thread-safe (the example routes run on threads)."""

    def __init__(self, max_bytes: int, frames: int) -> None:
        self.max_bytes = max_bytes
        self.frames = frames
        self.simulations = 0  # sequences simulated since start (the tests count them)
        self._kept: OrderedDict[tuple, ExampleSequence] = OrderedDict()
        self._lock = threading.Lock()  # guards _kept and _making
        self._making: dict[tuple, threading.Lock] = {}
        self._simulating = threading.Lock()  # one simulation at a time, service-wide

    def get(self, profile: RadarProfile, seed: int) -> ExampleSequence:
        """The example of ``profile`` with ``seed``, simulated now if no request made it yet; NoExamples for a
        radar with classes the simulator does not know."""
        if unknown := unknown_classes(profile):
            raise NoExamples(f"the simulator has no scatterer model for the radar's classes "
                             f"{', '.join(ascii(name) for name in unknown)}; known: {', '.join(sorted(CLASS_MODELS))}")
        key = (profile.fingerprint, profile.name, profile.class_names, seed)
        with self._lock:
            if key in self._kept:
                self._kept.move_to_end(key)
                return self._kept[key]
            making = self._making.setdefault(key, threading.Lock())
        with making:  # the first request simulates; the others wait here, then find it kept
            with self._lock:
                if key in self._kept:
                    return self._kept[key]
            with self._simulating:
                sequence = self._simulate(profile, seed)
            with self._lock:
                self._keep(key, sequence)
                self._making.pop(key, None)
        return sequence

    def _simulate(self, profile: RadarProfile, seed: int) -> ExampleSequence:
        self.simulations += 1
        frames, first = [], None
        for frame in simulate_sequence(profile, self.frames, seed=seed):
            first = first or frame
            buffer = io.BytesIO()
            np.save(buffer, frame.cube)
            frames.append(buffer.getvalue())
        assert first is not None
        return ExampleSequence(tuple(frames), tuple(first.cube.shape), first.cube.dtype.name, tuple(first.objects))

    def _keep(self, key: tuple, sequence: ExampleSequence) -> None:
        self._kept[key] = sequence
        while len(self._kept) > 1 and sum(s.nbytes for s in self._kept.values()) > self.max_bytes:
            self._kept.popitem(last=False)
