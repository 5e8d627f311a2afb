"""The model pool: each served model is loaded once and runs off the event loop, one request at a time
per replica, behind a bounded queue.

``EraseNet.segment`` is not safe to run concurrently on one instance (per-call MAC counters), so each
replica is used by one inference thread at a time. The process has ``replicas`` long-lived inference
threads, shared by every served model (one pool per model gave two models on 2 cores two OpenMP
teams sized to all the cores, and the service ran 3-5x slower than a plain process); each sets its torch
intra-op threads itself (``Settings.inference_threads``, the cores shared among the replicas) and runs
the warm-up too, so that torch's OpenMP thread teams never exceed the cores, whatever number of models is
served, and each is built once, on the thread that uses it. (Inference on a fresh worker thread with
torch's default threads was measured 4x slower than on the main thread.)

A request takes a slot of its model once its body has been read (a slow upload holds no slot) and
keeps it until its inference has finished; when ``replicas + max_queue`` slots are taken the request is
refused at once (503 with Retry-After) instead of piling up.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.checkpoint import CheckpointError
from models.erasenet.model import EraseNet, SegmentationResult
from models.runtime import load_erasenet
from radar.adc import process_adc
from radar.input_kind import InputKind
from radar.track_priors import TrackPriors
from service.radar_check import radar_refusal
from service.settings import ModelSpec, Settings, resolve_path

log = logging.getLogger(__name__)


class Saturated(Exception):
    """Every slot of a model is taken (running or queued)."""


class NotReady(Exception):
    """The model did not load (missing or bad checkpoint); the message says why."""


@dataclass
class ServedModel:
    """One served model: its replicas, worker threads and admission counter."""

    spec: ModelSpec
    capacity: int
    nets: list[EraseNet] = field(default_factory=list)
    error: str | None = "not loaded yet"
    stage: str = "waiting"  # what its loading does now: waiting, loading checkpoints, warming up, ready, failed
    segment_macs_high: int = 0  # largest segment MACs of the warm-up scenes: a new tenant's reservation estimate
    _free: queue.SimpleQueue = field(default_factory=queue.SimpleQueue)
    _executor: ThreadPoolExecutor | None = None
    _owns_executor: bool = True
    _held: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def ready(self) -> bool:
        return self.error is None and bool(self.nets)

    @property
    def net(self) -> EraseNet:
        """A replica for read-only facts (profile, params, detector MACs)."""
        if not self.ready:
            raise NotReady(f"model {self.spec.name!r} is not ready: {self.error}")
        return self.nets[0]

    @property
    def held(self) -> int:
        """Slots taken: requests running or waiting."""
        return self._held

    def load(self, replicas: int, warmup: bool, threads: int = 1, executor: ThreadPoolExecutor | None = None) -> None:
        """Build the replicas from the checkpoints and run them on ``executor`` (the pool's inference threads),
        or on a pool of its own of one inference thread per replica, each with ``threads`` torch threads; on
        failure record why (the service stays up, not ready)."""
        detector, segmenter = resolve_path(self.spec.detector), resolve_path(self.spec.segmenter)
        self._owns_executor = executor is None
        if executor is None:
            executor = inference_executor(replicas, threads, f"model-{self.spec.name}")

        def build() -> EraseNet:
            return load_erasenet(detector, segmenter, self.spec.runtime,
                                 score_threshold=self.spec.score_threshold, max_objects=self.spec.max_objects)

        # Built and warmed on the inference threads themselves: no other thread of the process runs torch, so
        # each replica's OpenMP team is the only one (a second team's idle threads compete for the cores).
        started = time.perf_counter()
        self.stage = "loading checkpoints"
        log.info("model %s: loading %s and %s (%d replica(s))", self.spec.name, detector, segmenter, replicas)
        try:  # one after the other: building (tracing) a model is not assumed to be thread-safe
            nets = [executor.submit(build).result() for _ in range(replicas)]
        except (CheckpointError, ValueError, KeyError, RuntimeError) as exc:
            if self._owns_executor:
                executor.shutdown(wait=True)
            self.error = str(exc)
            self.stage = "failed"
            log.error("model %s not loaded: %s", self.spec.name, exc)
            return
        self._executor = executor
        loaded = time.perf_counter()
        if warmup:
            self.stage = "warming up"
            log.info("model %s: loaded in %.1f s, warming up", self.spec.name, loaded - started)
            for done in [executor.submit(self._warm, net) for net in nets]:
                done.result()
        for net in nets:
            self._free.put(net)
        self.nets = nets
        self.error = None
        self.stage = "ready"
        log.info("model %s ready: preset %s, %d replica(s) (load %.1f s, warm-up %.1f s)", self.spec.name,
                 nets[0].profile.name, replicas, loaded - started, time.perf_counter() - loaded)

    def _warm(self, net: EraseNet) -> None:
        """Inference on a simulated point target (the first torch call of a thread is slow) and on a simulated
        scene of the preset, whose segmenter MACs start the quota reservation's estimate."""
        from radar.simulate import point_target_cube, simulate_sequence

        profile = net.profile
        cubes = [point_target_cube(profile, profile.max_range / 3, 0.0, 1.0, rcs_dbsm=20.0, noise=True, seed=0)]
        cubes += [frame.cube for frame in simulate_sequence(profile, 1, seed=0)]
        for cube in cubes:
            result = net.segment(cube)
            self.segment_macs_high = max(self.segment_macs_high, result.compute.segment_macs)

    def acquire(self) -> None:
        """Take a slot or raise Saturated."""
        with self._lock:
            if self._held >= self.capacity:
                raise Saturated(f"model {self.spec.name!r} has {self._held} requests running or queued")
            self._held += 1

    def release(self) -> None:
        with self._lock:
            self._held -= 1

    async def run(self, cube: np.ndarray, *, kind: InputKind, tdm_compensation: bool = True,
                  views: bool = False, history: list[np.ndarray | None] | None = None,
                  priors: TrackPriors | None = None) -> SegmentationResult:
        """Segment on an inference thread; the slot (taken by :meth:`acquire`) is released when inference ends,
        even if the awaiting request was cancelled. ``kind`` says what ``cube`` holds (radar.input_kind); ADC
        samples are processed into the RAD cube first (with ``tdm_compensation`` or without; timed as transform), once:
        ``views`` has the model return the input's RA/RD views from the same frame, inside its compute.
        ``history`` (a stream's frame, for a detector that reads earlier frames): their log power, the latest
        first; the result then keeps this frame's log power for the next one. ``priors``: where the stream's tracks
        expect their objects (radar.track_priors)."""
        if self._executor is None:
            self.release()
            raise NotReady(f"model {self.spec.name!r} is not ready: {self.error}")
        future = self._executor.submit(self._segment, cube, kind, tdm_compensation, views, history, priors)
        future.add_done_callback(lambda _: self.release())
        return await asyncio.wrap_future(future)

    def _segment(self, cube: np.ndarray, kind: InputKind, tdm_compensation: bool, views: bool = False,
                 history: list[np.ndarray | None] | None = None,
                 priors: TrackPriors | None = None) -> SegmentationResult:
        net = self._free.get()
        try:
            adc_s = 0.0
            if kind is InputKind.adc:
                start = time.perf_counter()
                cube, kind = process_adc(cube, net.profile, tdm_compensation=tdm_compensation), InputKind.complex
                adc_s = time.perf_counter() - start
            result = net.segment(cube, kind=kind, views=views, history=history,
                                 keep_log_power=history is not None, priors=priors)
            result.compute = result.compute.plus_seconds("transform", adc_s)
        finally:
            self._free.put(net)
        return result

    def close(self) -> None:
        if self._executor is not None and self._owns_executor:
            self._executor.shutdown(wait=True, cancel_futures=True)
        self._executor = None


def inference_executor(workers: int, threads: int, name: str) -> ThreadPoolExecutor:
    """``workers`` inference threads, each with ``threads`` torch threads."""
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name, initializer=set_torch_threads,
                              initargs=(threads,))


def set_torch_threads(threads: int) -> None:
    """Initializer of an inference thread: torch's intra-op thread count applies per calling thread."""
    import torch

    torch.set_num_threads(threads)


class ModelPool:
    """Every model of the settings, by name."""

    def __init__(self, settings: Settings) -> None:
        capacity = settings.replicas + settings.max_queue
        self.settings = settings
        self.models = {spec.name: ServedModel(spec, capacity) for spec in settings.models}
        self.default = settings.default_model_name
        self._executor: ThreadPoolExecutor | None = None
        self.loading = True  # until load() has tried every model

    def load(self) -> None:
        """Load every model (blocking: call from a thread or at start-up) onto one set of ``replicas`` inference
        threads shared by all models, so that their OpenMP teams together never exceed the cores."""
        threads = self.settings.inference_threads
        try:
            self._executor = inference_executor(self.settings.replicas, threads, "inference")
            for model in self.models.values():
                if refused := radar_refusal(model.spec, self.settings):  # before any network is built
                    model.error, model.stage = refused, "failed"
                    log.error("model %s not loaded: %s", model.spec.name, refused)
                    continue
                model.load(self.settings.replicas, self.settings.warmup, threads, executor=self._executor)
        finally:
            self.loading = False

    def progress(self) -> dict[str, str]:
        """Each model's loading stage (waiting, loading checkpoints, warming up, ready, failed)."""
        return {name: model.stage for name, model in self.models.items()}

    def get(self, name: str | None) -> ServedModel:
        """The model called ``name`` (the default when None); KeyError names the served ones."""
        name = name or self.default
        if name not in self.models:
            raise KeyError(f"unknown model {name!r}; served models: {sorted(self.models)}")
        return self.models[name]

    @property
    def ready(self) -> bool:
        return all(m.ready for m in self.models.values())

    def errors(self) -> dict[str, str | None]:
        return {name: m.error for name, m in self.models.items()}

    def close(self) -> None:
        for model in self.models.values():
            model.close()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def describe(self) -> list[dict[str, Any]]:
        """Facts about each model for GET /v1/models."""
        out = []
        for name, model in self.models.items():
            info: dict[str, Any] = {
                "name": name, "ready": model.ready, "error": model.error,
                "score_threshold": model.spec.score_threshold, "max_objects": model.spec.max_objects,
                "detector_checkpoint": str(model.spec.detector), "segmenter_checkpoint": str(model.spec.segmenter),
            }
            if model.ready:
                net = model.net
                info.update(preset=net.profile.name, shape=list(net.profile.shape), class_names=list(net.class_names),
                            params={**net.params, "total": sum(net.params.values())},
                            detector_macs=net.detector_macs())
            out.append(info)
        return out
