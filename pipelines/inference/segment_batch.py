"""Ray job: segment a whole store split or recording with ERASE-Net checkpoints into a predictions store.

::

    python -m pipelines.inference.segment_batch --source store:STORE.zarr --split test \\
        --detector checkpoints/detector.pt --segmenter checkpoints/segmenter.pt --out PRED.zarr
    python -m pipelines.inference.segment_batch --source recording:DIR --detector DET.pt --segmenter SEG.pt \\
        --out PRED.zarr
    ray job submit --address http://127.0.0.1:8265 --working-dir . -- \\
        python -m pipelines.inference.segment_batch ... --out /abs/PRED.zarr --workers 4

The job follows :mod:`pipelines.jobs` (its options and config in :mod:`pipelines.inference.segment_batch_options`)
and runs on :mod:`pipelines.datasets.sharded_job` like :mod:`pipelines.datasets.preprocess` (embedded local Ray
without ``--address``; ``RAY_ADDRESS`` under ``ray job submit``; ``--in-process`` for smoke runs without Ray). The
work is cut the same way: the selected frames take ``N`` slots of the predictions store
(:mod:`pipelines.inference.predictions_store`), every array is cut along the frame axis every ``--shard-frames``
slots, and a shard is the unit of work, of writing and of resumption.

Stages are callable classes (Ray's batch-inference pattern): ``--workers`` :class:`ShardSegmenter`
actors each load both checkpoints once (``__init__``), then each call reads its shard's frames from
the source, segments them and writes the whole shard of every array, then the shard's progress marker
(last). Actors are spread over the cluster's nodes; the runner keeps every actor busy (``ray.wait``).
A rerun with the same arguments skips shards whose marker exists; a store written with other
arguments is refused. Frames that cannot be read or segmented are quarantined (``valid = 0``, reason
in the ``report`` attribute); the job fails when every frame is bad. After the last shard and before the store
is marked complete, one sequential pass per sequence tracks its objects (:mod:`pipelines.inference.batch_tracks`:
the array ``tracks``, each object's track id and velocity vector).

The figure the job returns (and prints) is ``frames_per_second``: frames segmented over the wall time
from the first shard submitted to the last shard written, with every actor's model already loaded.
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from models.heap import freeze_loaded_heap
from models.runtime import Runtime
from pipelines.datasets import shard_frames, sharded_job
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.sharded_store import check_resumable_out, mark_shard_done, write_shard_arrays
from pipelines.datasets.sources import SourceKind, parse_source
from pipelines.datasets.store import frames_of_split, open_store
from pipelines.inference.predictions_store import (
    COMPUTE_FIELDS,
    FORMAT,
    PREDICTION_OBJECT_FIELDS,
    PredictionLayout,
    create_predictions,
    encode_prediction,
)
from pipelines.inference.segment_batch_options import (  # noqa: F401 (the job's options: pipelines.jobs' contract)
    SOURCE_KINDS,
    SegmentBatchConfig,
    add_arguments,
    config_from_args,
)
from pipelines.jobs import run_module
from radar import transforms
from radar.centres import MAX_OBJECTS, SCORE_THRESHOLD
from radar.errors import DataError, UserError
from radar.input_kind import InputKind
from radar.io.recording import Recording
from radar.profiles import describe_for_storage

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class FrameRef(sharded_job.FrameSlot):
    """One frame to segment: where it is in the source and which slot it takes in the predictions."""

    source_slot: int  # store slot, or running number over the recording's frames

    def slot_arrays(self) -> dict[str, int]:
        return {**super().slot_arrays(), "source_slot": self.source_slot}


@dataclass(frozen=True)
class BatchPlan(sharded_job.ShardedPlan):
    """Everything fixed before any work: the source, the predictions' layout, the slot of every frame
    (``FrameRef``s) and the checkpoints."""

    checkpoints: dict[str, Any]
    class_names: tuple[str, ...]

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run that created the store."""
        return {"source": self.source.to_dict(), "split": self.cfg.split, "layout": self.layout.to_dict(),
                "checkpoints": self.checkpoints, "score_threshold": self.cfg.score_threshold,
                "source_slots": [f.source_slot for f in self.frames]}


# --------------------------------------------------------------------------- planning
def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def plan_job(cfg: SegmentBatchConfig) -> BatchPlan:
    """Check every argument, the checkpoints' metadata and the source, and lay out the predictions store.
    Raises ValueError (CheckpointError is one) or DataError saying what is wrong; nothing is written."""
    from models.capabilities import Stage
    from models.checkpoint import load_checkpoint

    source_of_frames = parse_source(cfg.source, SOURCE_KINDS)
    kind, location = source_of_frames.kind, source_of_frames.location or ""
    for name in ("workers", "shard_frames", "max_objects", "limit", "torch_threads"):
        value = getattr(cfg, name)
        if value is not None and value < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if cfg.cpus_per_worker <= 0:
        raise UserError(f"--cpus-per-worker must be > 0, got {cfg.cpus_per_worker}")
    if not 0.0 <= cfg.score_threshold <= 1.0:
        raise UserError(f"--score-threshold must be in [0, 1], got {cfg.score_threshold}")
    if kind is SourceKind.RECORDING and cfg.split is not None:
        raise UserError("--split: only with a store source (a recording is segmented whole)")

    det = load_checkpoint(cfg.detector, stage=Stage.DETECTOR, option="--detector")
    seg = load_checkpoint(cfg.segmenter, stage=Stage.SEGMENTER, option="--segmenter")
    if det.preset != seg.preset:
        raise UserError(f"detector {cfg.detector} is for preset {det.preset!r} but segmenter {cfg.segmenter} "
                         f"for {seg.preset!r}")
    root_path = Path(location).expanduser().absolute()
    frames: list[FrameRef] = []
    if kind is SourceKind.STORE:
        root = open_store(root_path)
        preset = root.attrs["preset"]
        sequences = tuple(root.attrs["sequences"])
        slots = frames_of_split(root, cfg.split)
        sequence_ids, frame_indices = root["sequence_id"][:], root["frame_index"][:]
        for slot in slots[: cfg.limit]:
            seq_id = int(sequence_ids[slot])
            frames.append(FrameRef(len(frames), seq_id, sequences[seq_id], int(frame_indices[slot]), int(slot)))
    else:
        recording = Recording(root_path)
        preset = recording.profile.name
        sequences = tuple(sorted(recording.sequences()))
        running = 0
        for seq_id, seq in enumerate(sequences):
            for index in range(recording.n_frames(seq)):
                frames.append(FrameRef(len(frames), seq_id, seq, index, running))
                running += 1
        frames = frames[: cfg.limit]
    if preset != det.preset:
        raise UserError(f"the source {root_path} holds {preset!r} frames but the checkpoints are for {det.preset!r}")
    if not frames:
        raise DataError(root_path, f"no valid frame to segment (split {cfg.split or 'all'})")
    layout = PredictionLayout(preset, len(frames), cfg.shard_frames, cfg.max_objects,
                              radar_file=describe_for_storage(det.profile))
    checkpoints = {name: {"path": str(Path(path)), "sha256": _file_sha256(Path(path)), "model": ckpt.model_name}
                   for name, path, ckpt in (("detector", cfg.detector, det), ("segmenter", cfg.segmenter, seg))}
    plan = BatchPlan(cfg=cfg, out=Path(cfg.out), source=sharded_job.SourceSpec(kind, str(root_path), preset),
                     layout=layout,
                     sequences=sequences, frames=tuple(frames), checkpoints=checkpoints,
                     class_names=tuple(det.class_names))
    _check_out(plan)
    return plan


def _check_out(plan: BatchPlan) -> None:
    """An existing ``--out`` must be empty, or a predictions store of the same job (which is then resumed)."""
    check_resumable_out(plan.out, store_format=FORMAT, identity=plan.identity(), what="radarseg predictions store")


# --------------------------------------------------------------------------- the segmenter stage
def _source_cubes(source: sharded_job.SourceSpec, frames: Sequence[FrameRef], history: int = 0
                  ) -> Iterator[tuple[FrameRef, tuple[np.ndarray, list[np.ndarray | None] | None] | DataError]]:
    """Each frame's cube (a store's: float16 log power in dB; a recording's: complex) with, for ``history`` > 0,
    its sequence's earlier frames' log power in dB (the latest first, None where there is none or it cannot be
    read), or the DataError reading the frame raised."""
    if source.kind == "store":
        root = open_store(source.path)
        inputs = root["input"]
        earlier = earlier_slots(root, history) if history else None
        for ref in frames:
            past = None if earlier is None else earlier_frames(inputs, earlier[ref.source_slot])
            yield ref, (inputs[ref.source_slot].astype(np.float32), past)
        return
    recording = Recording(source.path)
    for ref in frames:
        try:
            cube = recording.read_frame(ref.sequence, ref.index).cube
        except DataError as exc:
            yield ref, exc
            continue
        past = [_recorded_log_power(recording, ref.sequence, ref.index - 1 - h) for h in range(history)]
        yield ref, (cube, past if history else None)


def _recorded_log_power(recording: Recording, sequence: str, index: int) -> np.ndarray | None:
    """A recording's frame as log power in dB, or None when it does not exist or cannot be read."""
    if index < 0:
        return None
    try:
        return transforms.log_power(recording.read_frame(sequence, index).cube)
    except DataError:
        return None


class ShardSegmenter:
    """Callable stage: loads ERASE-Net once (in ``__init__``), then segments and writes one shard per call.

    Used as a Ray actor (one per ``--workers``); plain instances run the same code in-process.
    """

    def __init__(self, detector: str, segmenter: str, *, score_threshold: float = SCORE_THRESHOLD,
                 max_objects: int = MAX_OBJECTS, torch_threads: int = 1, runtime: str = "torch") -> None:
        import torch

        from models.runtime import load_erasenet

        torch.set_num_threads(torch_threads)  # the ONNX engine takes its thread count from torch's too
        started = time.perf_counter()
        self.net = load_erasenet(detector, segmenter, runtime,
                                 score_threshold=score_threshold, max_objects=max_objects)
        # One inference on a noise-floor frame: the first torch call of a process is slow, and it should
        # not count against the first shard.
        self.net.segment(np.zeros(self.net.profile.shape, np.float32), kind=InputKind.log_power)
        freeze_loaded_heap()  # no full garbage collection over torch and the model every few frames
        self.model_loads = 1
        self.load_seconds = time.perf_counter() - started
        self.calls = 0

    def identity(self) -> dict[str, Any]:
        """Where this stage runs and how often it loaded the model (once)."""
        return {"pid": os.getpid(), "node_id": _node_id(), "model_loads": self.model_loads,
                "load_seconds": self.load_seconds}

    def __call__(self, job: sharded_job.ShardJob) -> dict[str, Any]:
        """Segment the frames of ``job``, write the whole shard of every array, then its marker; returns
        (and stores in the marker) the shard's summary."""
        self.calls += 1
        layout = job.layout
        kind = InputKind.log_power if job.source.kind == "store" else InputKind.complex  # a recording: complex cubes
        seconds = []

        def segment(frame: tuple[np.ndarray, list[np.ndarray | None] | None]) -> dict[str, np.ndarray]:
            cube, history = frame  # a cube of the wrong shape raises ValueError
            tick = time.perf_counter()
            result = self.net.segment(cube, kind=kind, history=history)
            seconds.append(time.perf_counter() - tick)
            return encode_prediction(result, layout)

        cubes = _source_cubes(job.source, job.frames, self.net.history_frames)
        buffers, quarantined = shard_frames.fill_shard(job, cubes, segment)
        write_shard_arrays(job.store, layout, job.shard, buffers)
        valid = buffers["valid"].astype(bool)
        summary = {
            "shard": job.shard,
            "frames": len(job.frames),
            "written": int(valid.sum()),
            "quarantined": quarantined,
            "objects": int(buffers["n_objects"][valid].sum()),
            "macs": int(buffers["compute"][valid, COMPUTE_FIELDS.index("macs_total")].sum()),
            "segment_seconds": sum(seconds),
            "worker": {**self.identity(), "calls": self.calls},
        }
        mark_shard_done(job.store, job.shard, summary)
        return summary


def _node_id() -> str | None:
    import ray

    if not ray.is_initialized():
        return None
    return ray.get_runtime_context().get_node_id()


# --------------------------------------------------------------------------- the job
REPORT_PICTURES = 3  # frames drawn in the report beside the store (most detections first)


def main(cfg: SegmentBatchConfig) -> dict[str, Any]:
    """Run the job; returns its figures (frames, written, quarantined, shards run/skipped, workers, frames/s)."""
    plan = plan_job(cfg)
    if Runtime.parse(cfg.runtime).backend == "onnx":  # exported once here, not in every actor at once (one cache)
        from models.checkpoint import load_pair
        from models.export.export_cache import exported_dir

        exported_dir(*load_pair(cfg.detector, cfg.segmenter))
    job = sharded_job.ShardedJob(plan=plan, create_store=create_predictions, stage=ShardSegmenter,
                                 stage_args=(cfg.detector, cfg.segmenter),
                                 stage_kwargs={"score_threshold": cfg.score_threshold, "max_objects": cfg.max_objects,
                                               "torch_threads": cfg.torch_threads, "runtime": cfg.runtime},
                                 reduce=reduce_summaries, finish=partial(finish_predictions, plan))
    execution = sharded_job.Execution(in_process=cfg.in_process, address=cfg.address, workers=cfg.workers,
                                      cpus_per_worker=cfg.cpus_per_worker, progress=cfg.progress, desc="segment")
    run = sharded_job.run_sharded(job, execution)
    per_worker: dict[int, dict[str, Any]] = {}
    for s in run.summaries:
        entry = per_worker.setdefault(s["worker"]["pid"], {**s["worker"], "shards": 0, "frames": 0})
        entry.update(calls=max(entry["calls"], s["worker"]["calls"]), shards=entry["shards"] + 1,
                     frames=entry["frames"] + s["frames"])
    stats = run.stats
    from pipelines.inference.predictions_report import (
        write_predictions_report,  # summary.json/.txt and pictures beside it
    )

    report = write_predictions_report(plan.out, pictures=REPORT_PICTURES)
    return {
        "store": str(plan.out),
        "report": report["dir"],
        "source": plan.source.to_dict(),
        "frames": stats["frames"],
        "written": stats["written"],
        "quarantined": len(stats["quarantined"]),
        "objects": stats["objects"],
        "macs_total": stats["macs"],
        "shards": plan.layout.n_shards,
        "shards_run": run.shards_run,
        "shards_skipped": run.shards_skipped,
        "workers": run.workers,
        "nodes": len({w["node_id"] for w in per_worker.values()}),
        "worker_stats": sorted(per_worker.values(), key=lambda w: w["pid"]),
        "seconds_ray_and_models": run.seconds_start,
        "seconds_segmenting": run.seconds_shards,
        "seconds_total": run.seconds_total,
        "frames_per_second": run.frames_per_second,
    }


def reduce_summaries(summaries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The job's figures from every shard's summary (given in shard order)."""
    return {
        "frames": sum(s["frames"] for s in summaries),
        "written": sum(s["written"] for s in summaries),
        "objects": sum(s["objects"] for s in summaries),
        "macs": sum(s["macs"] for s in summaries),
        "quarantined": sorted((q for s in summaries for q in s["quarantined"]), key=lambda q: q["frame"]),
    }


def finish_predictions(plan: BatchPlan, stats: dict[str, Any]) -> dict[str, Any]:
    """After every shard, before ``complete``: the final attributes, and the tracks of every sequence (one
    sequential pass, :mod:`pipelines.inference.batch_tracks`; its figures in the attribute ``tracking``)."""
    from pipelines.inference.batch_tracks import write_tracks

    attributes = store_attributes(plan, stats)
    return {**attributes, "tracking": write_tracks(plan.out, plan.layout.profile)}


def store_attributes(plan: BatchPlan, stats: dict[str, Any]) -> dict[str, Any]:
    """The predictions store's final attributes (DataError when every frame failed to segment)."""
    if stats["written"] == 0:
        raise DataError(plan.source.path, f"every one of the {stats['frames']} frames failed to segment (first: "
                                          f"{stats['quarantined'][0]['reason'] if stats['quarantined'] else '?'})")
    return {
        "preset": plan.layout.preset,
        "radar_file": plan.layout.radar_file,
        "class_names": list(plan.class_names),
        "sequences": list(plan.sequences),
        "object_fields": list(PREDICTION_OBJECT_FIELDS),
        "compute_fields": list(COMPUTE_FIELDS),
        "source": plan.source.to_dict(),
        "split": plan.cfg.split,
        "checkpoints": plan.checkpoints,
        "report": {"frames": stats["frames"], "written": stats["written"], "objects": stats["objects"],
                   "macs": stats["macs"], "quarantined": stats["quarantined"]},
        "job": plan.cfg.to_dict(),
    }


def format_result(result: dict[str, Any]) -> str:
    """The summary line (``--json`` prints the figures as one JSON line instead: what drivers of ``ray job
    submit`` read)."""
    return (f"predictions {result['store']}: {result['written']}/{result['frames']} frames segmented, "
            f"{result['quarantined']} quarantined, {result['shards_run']} shards run, "
            f"{result['shards_skipped']} already done; {result['frames_per_second'] or 0:.2f} frames/s with "
            f"{result['workers']} worker(s) on {result['nodes']} node(s); summary and pictures in {result['report']}")


if __name__ == "__main__":
    sys.exit(run_module("pipelines.inference.segment_batch"))
