"""The runner of the jobs that write a sharded store: :mod:`pipelines.datasets.preprocess` and
:mod:`pipelines.inference.segment_batch`.

A job plans its work (every argument checked, the store's layout and the frame of every slot fixed) and
hands the runner a :class:`ShardedJob`. The runner

1. creates the store or, when ``out`` already holds one of the same job (the plan checked that), skips
   the shards whose progress markers exist, so an interrupted job resumes;
2. runs the job's stage on each remaining shard (:class:`ShardJob` in, the shard's summary out; the
   stage writes the whole shard, then its marker). On Ray, at most ``workers`` shards are in flight
   (``ray.wait``): a function stage runs as Ray tasks, a class stage (Ray's batch-inference pattern: it
   loads its state once, in ``__init__``) as ``workers`` actors spread over the nodes. In-process
   (``in_process``, the smoke mode that tests and benchmarks use) the stage runs in the calling
   process, one shard after another, without Ray: the same store, byte for byte;
3. reduces every shard's summary (the job's ``reduce``, given them in shard order so that the result
   does not depend on timing), lets the job check the figures and name the final attributes
   (``finish``), writes them with the code version and, last, ``complete``.

Every shard summary holds ``shard`` and ``frames`` (slots in the shard). Also here, shared by both jobs:
the execution arguments. Elsewhere: what a stage reads and writes per shard (:mod:`pipelines.datasets.shard_frames`),
the Ray start-up (:mod:`pipelines.ray_runtime`) and the code version (:mod:`pipelines.datasets.provenance`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipelines.datasets.provenance import code_version
from pipelines.datasets.shard_frames import FrameSlot, ShardJob, SourceSpec
from pipelines.datasets.sharded_store import Sharded, done_shards, finish_store
from pipelines.progress import progress
from pipelines.ray_runtime import init_ray

log = logging.getLogger(__name__)

Stage = Callable[[ShardJob], dict[str, Any]]


@dataclass(frozen=True)
class ShardedPlan:
    """What a sharded job fixes before any work (its ``plan_job`` checks every argument and the source)."""

    cfg: Any  # the job's config (``to_dict()`` is recorded in the store)
    out: Path
    source: SourceSpec
    layout: Sharded
    sequences: tuple[str, ...]  # names, indexed by ``sequence_id``
    frames: tuple[FrameSlot, ...]  # one per slot of the store

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run that created the store."""
        raise NotImplementedError


@dataclass(frozen=True)
class ShardedJob:
    """A planned job as the runner needs it."""

    plan: ShardedPlan
    create_store: Callable[[Path, Any, dict[str, Any]], Any]  # (path, layout, attributes): the empty store
    stage: Stage | type  # a function, or a class whose instances are stages (loaded once per worker)
    reduce: Callable[[Sequence[dict[str, Any]]], dict[str, Any]]  # every shard's summary -> the job's figures
    finish: Callable[[dict[str, Any]], dict[str, Any]]  # figures -> final attributes (DataError: nothing usable)
    stage_args: tuple[Any, ...] = ()  # a class stage's constructor arguments
    stage_kwargs: Mapping[str, Any] = field(default_factory=dict)

    def shard_job(self, shard: int) -> ShardJob:
        plan = self.plan
        start, stop = plan.layout.shard_bounds(shard)
        return ShardJob(str(plan.out), plan.layout, plan.source, shard, plan.frames[start:stop])


@dataclass(frozen=True)
class Execution:
    """Where the shards run: Ray (``address`` None: an embedded local Ray, or ``RAY_ADDRESS`` under
    ``ray job submit``) or, with ``in_process``, this process."""

    in_process: bool = False
    address: str | None = None
    workers: int | None = None  # shards in flight; None = the cluster's CPUs / cpus_per_worker
    cpus_per_worker: float = 1.0
    progress: bool = True
    desc: str = "shards"  # progress bar label


@dataclass(frozen=True)
class ShardedRun:
    """What a run did: the job's reduced figures, the new shards' summaries, and its timing."""

    stats: dict[str, Any]
    summaries: tuple[dict[str, Any], ...]  # of the shards run now, in shard order
    shards_run: int
    shards_skipped: int
    workers: int  # shards in flight at most (tasks), or actors; 1 in-process
    seconds_start: float  # store created, Ray connected, every class stage loaded
    seconds_shards: float  # first shard submitted to last shard written
    seconds_total: float

    @property
    def frames_per_second(self) -> float | None:
        frames = sum(s["frames"] for s in self.summaries)
        return frames / self.seconds_shards if frames else None


def run_sharded(job: ShardedJob, execution: Execution) -> ShardedRun:
    """Create or resume the store, run the stage on every shard not done, finish the store."""
    plan = job.plan
    started = time.perf_counter()
    if (plan.out / "zarr.json").is_file():
        done = done_shards(plan.out)
    else:
        done = {}
        job.create_store(plan.out, plan.layout, {"plan": plan.identity(), "job": plan.cfg.to_dict()})
    todo = [s for s in range(plan.layout.n_shards) if s not in done]
    backend = _InProcess(job) if execution.in_process else _OnRay(job, execution)
    new: list[dict[str, Any]] = []
    try:
        workers = backend.start(len(todo))
        ready = time.perf_counter()
        log.info("%s: %d shards (%d done before), %d worker(s) %s", plan.out, plan.layout.n_shards, len(done),
                 workers, backend.where)
        with progress(total=plan.layout.n_frames, initial=sum(s["frames"] for s in done.values()), unit="frame",
                  desc=execution.desc, disable=not execution.progress) as bar:
            for summary in backend.run(todo):
                new.append(summary)
                bar.update(summary["frames"])
        processed = time.perf_counter()
    finally:
        backend.close()
    new.sort(key=lambda s: s["shard"])
    every = sorted([*done.values(), *new], key=lambda s: s["shard"])
    stats = job.reduce(every)
    finish_store(plan.out, {**job.finish(stats), "code_version": code_version()})  # `complete` goes last
    return ShardedRun(stats, tuple(new), len(todo), len(done), workers, ready - started, processed - ready,
                      time.perf_counter() - started)


class _InProcess:
    """Every shard in the calling process, in order; a class stage is built once."""

    where = "in this process"

    def __init__(self, job: ShardedJob) -> None:
        self.job = job
        self.stage: Stage | None = None

    def start(self, n_todo: int) -> int:
        stage = self.job.stage
        if isinstance(stage, type):
            if not n_todo:
                return 0
            stage = stage(*self.job.stage_args, **self.job.stage_kwargs)
        self.stage = stage
        return 1

    def run(self, shards: Sequence[int]) -> Iterator[dict[str, Any]]:
        for shard in shards:
            yield self.stage(self.job.shard_job(shard))

    def close(self) -> None:
        self.stage = None


class _OnRay:
    """Shards as Ray tasks (function stage) or on actors (class stage), at most ``workers`` in flight."""

    def __init__(self, job: ShardedJob, execution: Execution) -> None:
        self.job, self.execution = job, execution
        self.connected = False
        self.actors: list[Any] = []
        self.where = "on Ray"

    def start(self, n_todo: int) -> int:
        import ray

        self.connected = init_ray(self.execution.address)
        cpus = self.execution.cpus_per_worker
        workers = self.execution.workers or max(1, int(float(ray.cluster_resources().get("CPU", 1)) // cpus))
        if not isinstance(self.job.stage, type):
            self.submit = ray.remote(num_cpus=cpus)(self.job.stage).remote
            self.slots: list[Any] = [None] * workers
            self.where = "(Ray tasks in flight)"
            return workers
        actor_class = ray.remote(num_cpus=cpus, scheduling_strategy="SPREAD")(self.job.stage)
        self.actors = [actor_class.remote(*self.job.stage_args, **self.job.stage_kwargs)
                       for _ in range(min(workers, n_todo))]
        identities = ray.get([a.identity.remote() for a in self.actors])  # every stage loaded before the clock
        self.slots = list(self.actors)
        self.where = f"(Ray actors on {len({i.get('node_id') for i in identities})} node(s))"
        return len(self.actors)

    def run(self, shards: Sequence[int]) -> Iterator[dict[str, Any]]:
        import ray

        queue = list(shards)
        running: dict[Any, Any] = {}  # object ref -> the slot (actor, or None for a task) it occupies
        while queue or running:
            while queue and self.slots:
                slot = self.slots.pop(0)
                payload = self.job.shard_job(queue.pop(0))
                running[self.submit(payload) if slot is None else slot.__call__.remote(payload)] = slot
            finished, _ = ray.wait(list(running), num_returns=1)
            for ref in finished:
                self.slots.append(running.pop(ref))
                yield ray.get(ref)  # a failed shard raises here

    def close(self) -> None:
        import ray

        for actor in self.actors:
            ray.kill(actor)
        if self.connected:
            ray.shutdown()
